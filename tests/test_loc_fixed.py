"""The fixed-point client-solve circuit (``nx-sil-nN``, normal_fixed.py): each fixed-point
operation's circuit equals its int64 mirror bit for bit, so does the whole circuit (on
random iterations, on saturating and far-spread scenes), its decoded normal equations are
the float64 ones to about 13 bits, and localizing on it lands where OpenCV does."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_loc_circuits import random_values

from snail_common.circuit import CircuitBuilder
from snail_common.circuit.cleartext import evaluate
from snail_common.circuit.ir import AND
from snail_common.circuit.schedule import schedule_circuit
from snail_common.loc.accuracy import compare_with_opencv, opencv_iterative
from snail_common.loc.backends import (
    Float64Backend,
    MirrorBackend,
    sil_values,
    step_about_camera,
)
from snail_common.loc.geometry import hat, pose_from_rvec_tvec
from snail_common.loc.pipeline import Options, _symmetric, localize
from snail_common.loc.preprocess import normalize
from snail_common.loc.synthetic import random_scene
from snail_common.loc.types import Pose
from snail_common.pnp.do import normal_equations64
from snail_common.pnp.fixed import SM, TC, FixMirror
from snail_common.pnp.fixed_circuit import FixCircuit
from snail_common.pnp.fops import CircuitBackend, F
from snail_common.pnp.fops import MirrorBackend as FloatMirror
from snail_common.pnp.normal_fixed import (
    D_COST,
    EMAX_A,
    F_W,
    H_SHIFT,
    T_BITS,
    W_A,
    W_C,
    W_MAP,
    W_RC,
    W_RS,
    camera_points_fixed,
    decode,
    map_block,
    map_fixed,
    normal_equations_fixed,
    weight_unit,
    weights_fixed,
)
from snail_common.pnp.sil import input_shapes
from snail_common.pnp.spec import Spec, build, run_mirror

N = 7
SPEC = Spec("lm", "sil", "client", N, arith="fixed")


@pytest.fixture(scope="module")
def compiled():
    circuit = build(SPEC)
    return circuit, schedule_circuit(circuit)


def test_ids_and_defaults():
    assert SPEC.circuit_id == "nx-sil-n7" and Spec.parse("nx-sil-n7") == SPEC
    assert Spec.parse("ne-sil-n7").arith == "float"
    assert Options().spec(6).circuit_id == "nx-sil-n6"
    assert Options(arith="float").spec(6).circuit_id == "ne-sil-n6"
    assert Options(solve="circuit").spec(6).circuit_id == "lm-sil-ldlt-n6-x"
    assert Options(solve="circuit", arith="fixed").spec(6).circuit_id == "lm-sil-ldlt-n6-x"
    assert Options(solve="circuit", solver="svd").spec(6).circuit_id == "lm-sil-svd-n6"
    with pytest.raises(ValueError, match="--arith fixed"):
        Options(mode="do", arith="fixed")


def _floats(rng: np.random.Generator, n: int) -> np.ndarray:
    """float32 values of every kind a conversion meets: zeros of both signs, subnormals,
    tiny, ordinary, beyond the saturation point, infinities."""
    mags = 2.0 ** rng.uniform(-30, 6, n)
    mags[:6] = [0.0, 1e-40, 2.0 ** -126, 1.999, 2.0, np.inf]
    return (mags * rng.choice([-1.0, 1.0], n)).astype(np.float32)


def test_conversions_products_and_sums_match_the_mirror():
    rng = np.random.default_rng(3)
    x, y = _floats(rng, 40), _floats(rng, 40)
    x[-1] = -0.0
    b = CircuitBuilder()
    fc = FixCircuit(CircuitBackend(b))
    wx, wy = (F(CircuitBackend(b), b.input(name, (40,), bits=32, dtype="float32"))
              for name in "xy")
    fm = FixMirror(FloatMirror())
    mx, my = F(FloatMirror(), x), F(FloatMirror(), y)
    results = []
    for fx, u, v in ((fc, wx, wy), (fm, mx, my)):
        pub = fx.from_float(u, EMAX_A, W_A)
        emax = fx.block_emax(v[6:])  # no infinity in this block
        blk = fx.from_float(v[6:], emax, 15)
        prod = fx.mul(pub[6:], blk, 13, 16)
        total = fx.sum_tc(fx.twos(prod))
        results.append((pub, emax, blk, prod, total))
    for name, wires, bits in (("pub_m", results[0][0].m, W_A), ("pub_s", results[0][0].s, 1),
                              ("emax", results[0][1], 8), ("blk_m", results[0][2].m, 15),
                              ("prod_m", results[0][3].m, 16), ("prod_s", results[0][3].s, 1),
                              ("total", results[0][4].v, results[0][4].w)):
        b.output(name, wires if bits > 1 else np.asarray(wires)[..., None],
                 dtype="int64" if name == "total" else None)
    out = evaluate(b.build(), {"x": x, "y": y})
    pub, emax, blk, prod, total = results[1]
    assert np.array_equal(out["pub_m"], pub.m) and np.array_equal(out["pub_s"], pub.s)
    assert pub.m[4] == pub.m[5] == (1 << W_A) - 1  # |a| >= 2 saturates
    assert pub.m[0] == pub.m[1] == 0  # zeros and subnormals are 0
    assert int(out["emax"]) == int(emax)
    assert np.array_equal(out["blk_m"], blk.m)
    assert np.array_equal(out["prod_m"], prod.m) and np.array_equal(out["prod_s"], prod.s)
    assert int(out["total"]) == int(total.v)


def test_wide_words_round_back_to_float_like_the_mirror():
    """to_float_scaled on 40-bit words: zeros, both signs, exact ties (round to even), the
    largest magnitudes, an exponent from a secret word plus a constant (9 bits)."""
    rng = np.random.default_rng(4)
    words = rng.integers(-(1 << 39), 1 << 39, 48)
    words[:8] = [0, 1, -1, (1 << 39) - 1, -(1 << 39) + 1, 3 << 30, 5 << 30, -(7 << 29)]
    words[8] = (1 << 24) + 1 << 10  # 25 significant bits: a tie, to even
    b = CircuitBuilder()
    fc = FixCircuit(CircuitBackend(b))
    wv = b.input("v", (48,), bits=40, dtype="int64")
    we = b.input("e", (), bits=8, dtype="uint8")
    for name, emax in (("public", 140), ("secret", fc.exponent_plus(we, 12))):
        b.output(name, fc.to_float_scaled(TC(wv, 40), emax, 26).v, dtype="float32")
    out = evaluate(b.build(), {"v": words, "e": np.uint8(128)})
    fm = FixMirror(FloatMirror())
    for name, emax in (("public", 140), ("secret", fm.exponent_plus(np.int64(128), 12))):
        want = fm.to_float_scaled(TC(words, 40), emax, 26).v
        assert np.array_equal(np.asarray(out[name]).view(np.uint32), want.view(np.uint32))
        assert want[8] == np.float32(2.0 ** 34 * 2.0 ** (int(emax) - 26 - 126))  # tie to even
    assert np.array_equal(want, (words * 2.0 ** (140 - 26 - 126)).astype(np.float32))


@pytest.mark.parametrize("cut", [1, 13, 21, 25])
def test_truncated_products_match_the_mirror_and_their_bound(cut):
    """mul_cut of 25 x 26 bit magnitudes, one operand broadcast (as R is over the points):
    bit for bit, and at most 2T / 2^(drop + 1 - cut) below the floor of the exact product
    (T = 15 radix-4 terms), never above it."""
    rng = np.random.default_rng(cut)
    xm = rng.integers(0, 1 << 25, (1, 6))
    ym = rng.integers(0, 1 << 26, (40, 1))
    xm[0, :2], ym[:4, 0] = [0, (1 << 25) - 1], [0, 1, (1 << 26) - 1, 1 << 25]
    xs, ys = rng.integers(0, 2, (1, 6)), rng.integers(0, 2, (40, 1))
    b = CircuitBuilder()
    fc = FixCircuit(CircuitBackend(b))
    wires = {name: b.input(name, shape, bits=bits) for name, shape, bits in
             (("xm", (1, 6), 25), ("ym", (40, 1), 26), ("xs", (1, 6), 1), ("ys", (40, 1), 1))}
    got = fc.mul_cut(SM(wires["xs"][..., 0], wires["xm"], 25), SM(wires["ys"][..., 0],
                     wires["ym"], 26), 24, cut, 28)
    b.output("p", got.v, dtype="int64")
    out = evaluate(b.build(), {"xm": xm, "ym": ym, "xs": xs, "ys": ys})["p"]
    want = FixMirror(FloatMirror()).mul_cut(SM(xs, xm, 25), SM(ys, ym, 26), 24, cut, 28)
    assert np.array_equal(out, want.v) and want.w == got.w == 29
    exact = (xm * ym) >> 24
    short = exact - np.where((xs ^ ys) == 1, -want.v, want.v)
    assert short.min() >= 0 and short.max() <= max(30 >> (25 - cut), 1)
    if cut == 21:
        assert short.max() >= 1  # the truncation shows


def test_truncated_products_in_sign_magnitude_match_the_mirror():
    """mul_cut_sm, the truncated product that feeds another product: its magnitude is
    mul_cut's floored at 0 (a zero operand's dropped carries make mul_cut -1), the signs
    XORed apart, bit for bit in the circuit."""
    rng = np.random.default_rng(9)
    xm, ym = rng.integers(0, 1 << 16, (30, 5)), rng.integers(0, 1 << 10, (30, 1))
    xm[:3], ym[3:5] = 0, 0
    xs, ys = rng.integers(0, 2, (30, 5)), rng.integers(0, 2, (30, 1))
    b = CircuitBuilder()
    fc = FixCircuit(CircuitBackend(b))
    wires = {name: b.input(name, shape, bits=bits) for name, shape, bits in
             (("xm", (30, 5), 16), ("ym", (30, 1), 10), ("xs", (30, 5), 1), ("ys", (30, 1), 1))}
    got = fc.mul_cut_sm(SM(wires["xs"][..., 0], wires["xm"], 16),
                        SM(wires["ys"][..., 0], wires["ym"], 10), 9, 6, 17)
    b.output("m", got.m, dtype="uint32")
    b.output("s", np.asarray(got.s)[..., None])
    out = evaluate(b.build(), {"xm": xm, "ym": ym, "xs": xs, "ys": ys})
    fm = FixMirror(FloatMirror())
    want = fm.mul_cut_sm(SM(xs, xm, 16), SM(ys, ym, 10), 9, 6, 17)
    assert np.array_equal(out["m"], want.m) and np.array_equal(out["s"], want.s ^ 0)
    unsigned = fm.mul_cut(SM(0 * xs, xm, 16), SM(0 * ys, ym, 10), 9, 6, 17).v
    assert unsigned.min() == -1 and want.m.min() == 0  # the clamp acts
    assert np.array_equal(want.m, np.maximum(unsigned, 0))
    assert np.all((want.m <= (xm * ym) >> 9) & (want.m >= ((xm * ym) >> 9) - 2))


@pytest.mark.parametrize("depth_opt", [False, True])
def test_reciprocals_in_block_floating_point_match_the_mirror(depth_opt):
    """recip_block: bit for bit (both adders), the floor of the exact 1/z at the block
    exponent from_float would use (one lower where the smallest z is a power of two, whose
    1/z then saturates); a zero saturates its own magnitude and flushes the others (as
    1/0 = inf did); negative z keep their sign."""
    rng = np.random.default_rng(12)
    z = (2.0 ** rng.uniform(-3, 6, 40) * rng.choice([-1.0, 1.0], 40, p=[0.1, 0.9])).astype(
        np.float32)
    z[:5] = [0.5, 1.0, np.nextafter(np.float32(1.0), np.float32(2.0)), 1.9999999, 0.0625]
    blocks = [z, np.concatenate([z[:39], [0.0]]).astype(np.float32), z * np.float32(2.0 ** 90)]
    b = CircuitBuilder()
    be = CircuitBackend(b, depth_opt=depth_opt)
    wz = F(be, b.input("z", (40,), bits=32, dtype="float32"))
    got, ec = FixCircuit(be).recip_block(wz, W_C)
    b.output("m", got.m, dtype="uint32")
    b.output("s", np.asarray(got.s)[..., None])
    b.output("e", ec, dtype="uint8")
    circuit = b.build()
    fm = FixMirror(FloatMirror())
    for i, block in enumerate(blocks):
        out = evaluate(circuit, {"z": block})
        want, want_e = fm.recip_block(F(FloatMirror(), block), W_C)
        assert np.array_equal(out["m"], want.m) and np.array_equal(out["s"], want.s), i
        assert int(out["e"]) == int(want_e), i
        if i == 1:
            assert want.m[39] == (1 << W_C) - 1 and not want.m[:39].any()
            continue
        inv = 1.0 / block.astype(np.float64)
        bits = block.view(np.uint32)
        e = (bits >> 23) & 0xFF
        top_pow2 = np.any((e == e.min()) & (bits & 0x7FFFFF == 0))  # 1/z a binade higher
        emax = int(fm.block_emax(F(FloatMirror(), inv.astype(np.float32))))
        assert int(want_e) == emax - int(top_pow2), i
        exact = np.floor(np.abs(inv) / 2.0 ** (int(want_e) - W_C - 126))
        assert np.array_equal(want.m, np.minimum(exact, (1 << W_C) - 1)), i
        assert want.m[4] == (1 << W_C) - 1  # 1/0.0625, the block's top: 2^W_C saturates
        assert np.array_equal(want.s, (block < 0).astype(np.int64))


def _camera_circuit(n: int):
    b = CircuitBuilder()
    be = CircuitBackend(b)
    R, t, world = (F(be, b.input(k, shape, bits=32, dtype="float32"))
                   for k, shape in (("R", (3, 3)), ("t", (3,)), ("world", (n, 3))))
    b.output("xc", camera_points_fixed(R, t, world).v, dtype="float32")
    return b.build()


def _camera_cases(rng: np.random.Generator, n: int) -> list[dict[str, np.ndarray]]:
    """Ordinary scenes, then the extremes: one point far out (the rest lose low bits),
    subnormal and zero coordinates, R entries of exactly +-1, t beyond its headroom
    (saturates), and a map so large or so small that the exponents reach their ends."""
    cases = []
    for _ in range(8):
        values = random_values(Spec("lm", "sil", "client", n, arith="fixed"), rng)
        cases.append({name: values[name] for name in ("R", "t", "world")})
    far, tiny, axes, sat, huge, small = (dict(c) for c in cases[2:])
    far["world"] = far["world"].copy()
    far["world"][0] = [30.0, -20.0, 10.0]
    tiny["world"] = tiny["world"].copy()
    tiny["world"][:3] = [[0.0, -0.0, 1e-40], [2.0 ** -126, 1e-30, -0.0], [0.0, 0.0, 0.0]]
    axes["R"] = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], np.float32)
    sat["t"] = np.array([1e5, -3.0, 7e4], np.float32)
    huge["world"], huge["t"] = huge["world"] * np.float32(2.0 ** 110), huge["t"] * 2 ** 110
    small["world"], small["t"] = small["world"] * np.float32(2.0 ** -110), small["t"] * 2 ** -110
    return cases + [far, tiny, axes, sat, huge, small]


def test_camera_points_in_fixed_point_match_the_mirror_and_their_error_bound():
    """Bit for bit on every case; against float64, within the bound derived in
    camera_points_fixed's doc wherever t is inside its headroom."""
    n = 9
    circuit = _camera_circuit(n)
    schedule = schedule_circuit(circuit)
    rng = np.random.default_rng(16)
    for i, values in enumerate(_camera_cases(rng, n)):
        got = evaluate(circuit, values, schedule=schedule)["xc"]
        fm = FloatMirror()
        want = camera_points_fixed(*(F(fm, values[k]) for k in ("R", "t", "world"))).v
        assert np.array_equal(np.asarray(got).view(np.uint32), want.view(np.uint32)), i
        v = {k: np.asarray(x, np.float64) for k, x in values.items()}
        top = np.abs(v["world"]).max()
        if np.abs(v["t"]).max() >= 2.0 ** T_BITS * top or not 2.0 ** -100 < top < 2.0 ** 100:
            continue
        exact = v["world"] @ v["R"].T + v["t"]
        bound = 12.5 * 2.0 ** -(W_MAP - 1) * top + 2.0 ** -24 * np.abs(exact)
        assert np.all(np.abs(want - exact) <= bound), i


def test_the_mirror_is_the_arithmetic_it_claims():
    """Magnitudes are the truncated values at the scale the module doc states."""
    fm = FixMirror(FloatMirror())
    v = np.array([1.5, -0.375, 1e-3, 3.0], np.float32)
    pub = fm.from_float(F(FloatMirror(), v), EMAX_A, W_A)
    scale = 2.0 ** (EMAX_A - W_A - 126)
    np.testing.assert_array_equal(pub.m[:3], np.floor(np.abs(v[:3]) / scale))
    assert pub.s.tolist() == [0, 1, 0, 0]
    emax = fm.block_emax(F(FloatMirror(), v))
    assert emax == 128  # 3.0 = 1.5 * 2^1
    blk = fm.from_float(F(FloatMirror(), v), emax, 15)
    np.testing.assert_array_equal(blk.m, np.floor(np.abs(v) / 2.0 ** (128 - 15 - 126)))


def test_the_client_passes_the_map_as_block_fixed_point():
    """nx-sil takes the map as the integers the in-circuit family converts it to (map_fixed:
    W_MAP-bit magnitudes at the largest exponent, the sign in bit W_MAP, the exponent
    apart), not as float32: the same sums and cost, bit for bit, for ~0.65 k AND per point
    less (the float map stays a value for the float64 backend, never a circuit input)."""
    shapes = input_shapes("lm", N, "client", "fixed")
    assert "world" not in shapes and shapes["wmap"] == (N, 3) and shapes["emap"] == ()
    assert "world" in input_shapes("lm", N, "ldlt", "fixed")  # the in-circuit family
    rng = np.random.default_rng(12)
    fm = FloatMirror()
    for i in range(4):
        values = random_values(SPEC, rng)
        values.pop("lam")
        if i == 1:  # a far point, a negative zero, a subnormal
            values["world"][:3] = [[3e3, -2e3, 50.0], [-0.0, 1.0, -2.0], [1e-40, -1.0, 0.5]]
        world = values["world"]
        wmap, emap = map_fixed(world)
        assert wmap.dtype == np.uint32 and int(wmap.max()) < 1 << (W_MAP + 1)
        assert int(emap) == int(((world.view(np.uint32) >> 23) & 0xFF).max())
        unit = 2.0 ** (int(emap) - W_MAP - 126)
        got = np.where(wmap >> W_MAP, -1.0, 1.0) * (wmap & ((1 << W_MAP) - 1)) * unit
        assert np.all((wmap >> W_MAP) == np.signbit(world))
        assert np.all(np.abs(got - world) < unit) and np.all(np.abs(got) <= np.abs(world))
        values["wfix"] = weights_fixed(values["weights"])
        x = {k: F(fm, np.asarray(v, np.float32)) for k, v in values.items()}
        want = normal_equations_fixed(x["R"], x["t"], x["image"], map_block(x["world"]),
                                      x["weights"], values["wfix"], H_SHIFT, W_RS)
        values["wmap"], values["emap"] = wmap, emap
        out = run_mirror(SPEC, {k: v for k, v in values.items() if k != "world"})
        for name, w in zip(("hess", "grad", "cost", "ec", "er", "el"), want, strict=True):
            assert np.array_equal(out[name], np.asarray(getattr(w, "v", w))), (i, name)


def test_cleartext_equals_mirror_on_random_iterations(compiled):
    circuit, schedule = compiled
    assert [g.name for g in circuit.inputs][-1] == "wfix"
    rng = np.random.default_rng(11)
    for i in range(6):
        values = random_values(SPEC, rng)
        values.pop("lam")
        if i == 1:
            values["image"][0] *= 40  # a residual far larger than the rest
        if i == 2:
            values["world"][1] = values["world"][1] * 0.05 + [2.0, 0.0, 0.0]  # |a| > 2
        if i == 3:  # zero residuals, one subnormal, the rest tiny; zero weights
            cam = values["world"] @ values["R"].T + values["t"]
            values["image"] = (cam[:, :2] / cam[:, 2:]).astype(np.float32)
            values["image"][1, 0] += np.float32(1e-40)
            values["weights"][2:5] = 0.0
        if i == 4:  # one point far out and huge residuals (not beyond float32)
            values["world"][0] = [3e3, -2e3, 50.0]
            values["image"][1] = [3e4, -3e4]
        values["wfix"] = weights_fixed(values["weights"])
        values["wmap"], values["emap"] = map_fixed(values.pop("world"))
        out = evaluate(circuit, values, schedule=schedule)
        mirror = run_mirror(SPEC, values)
        for name, got in out.items():
            assert np.array_equal(np.asarray(got), np.asarray(mirror[name])), (i, name)


def test_the_fixed_point_cost_is_within_its_bound():
    """The cost in fixed point against the exact sum of the weights (wfix: their square
    roots s) times the float32 residuals' squares, never above it: with sigma = s r / u
    (u the residuals' unit), s r is truncated to less than 3 units below sigma (the
    residual's floor, the product's floor and its cut partial products), which loses less
    than 6 sigma u^2 of s^2 r^2, and its square with its cut partial products less than 2
    units of 2^D_COST. With equal weights and the largest residual a weighted one (at
    least 2^(W_RC - 1) u) that is below 6 sqrt(2n) 2^(1 - W_RC) + n 2^(D_COST + 4 -
    2 W_RC) of the cost (Cauchy-Schwarz: 2.7e-4 at n = 256 with W_RC = 20; measured
    here at most 1.0e-5, 3e-7 with W_RC = 24); these scenes, some with the
    largest residual unweighted or fx != fy, stay below it too. Zero weights, zero, tiny
    and huge residuals, n = 4 to 256."""
    rng = np.random.default_rng(30)
    fm = FloatMirror()
    for i in range(24):
        n = [4, 7, 64, 256][i % 4]
        values = random_values(Spec("lm", "sil", "client", n, arith="fixed"), rng)
        values["image"] += rng.normal(0, 10.0 ** rng.uniform(-6, 0), (n, 2)).astype(np.float32)
        if i % 6 == 5:
            values["image"][0] *= np.float32(1e4)
        if i % 6 == 4:
            values["weights"][:, 1] *= np.float32(rng.uniform(0.2, 1.0))  # fx != fy
        wfix = weights_fixed(values["weights"])
        x = {k: F(fm, np.asarray(v, np.float32)) for k, v in values.items()}
        _, _, cost, ec, er, _ = normal_equations_fixed(x["R"], x["t"], x["image"],
                                                       map_block(x["world"]), x["weights"],
                                                       wfix)
        xc = camera_points_fixed(x["R"], x["t"], x["world"])
        err = xc[:, 0:2] / xc[:, 2:3] - x["image"]
        unit = 2.0 ** (int(er) - W_RC - 126)
        rho = np.abs(err.v.astype(np.float64)) / unit
        sigma = wfix.astype(np.float64) / 2.0 ** F_W * rho
        exact = float(np.sum(sigma ** 2))
        got = float(cost.v) * 2.0 ** D_COST
        assert 0 <= exact - got <= float(np.sum(6 * sigma)) + 4 * n * 2.0 ** D_COST, i
        rel = 6 * np.sqrt(2 * n) * 2.0 ** (1 - W_RC) + n * 2.0 ** (D_COST + 4 - 2 * W_RC)
        assert exact - got <= rel * exact, i
        outd = decode(values["weights"], 0, {"hess": np.zeros(21), "grad": np.zeros(6),
                                             "cost": cost.v, "ec": ec, "er": er,
                                             "el": np.zeros(3)})
        assert outd["cost"] == got * unit ** 2 * weight_unit(values["weights"])


def _about_origin(hess, grad, t):
    """backends.about_camera's inverse: the sums of the step that rotates about the map's
    origin (v' = v - [t]x w)."""
    inv = np.eye(6)
    inv[:3, 3:] = hat(np.asarray(t, np.float64))
    return inv.T @ hess @ inv, inv.T @ grad


def _system64(values):
    v = {k: np.asarray(x, np.float64) for k, x in values.items()}
    return normal_equations64(v["R"], v["t"], v["image"], v["world"], v["weights"])


@pytest.mark.parametrize("planar,weighted", [(False, False), (True, False), (False, True)])
def test_decoded_normal_equations_are_the_float64_ones(planar, weighted):
    """Also with unequal weights (lens distortion, fx != fy, padding): the sums take
    sqrt(w) at 10 bits (weights off by up to 2^-9 / sqrt(w / w_max), 2^-8 here: 4.4e-3 and
    2.0e-3 for J^T W J and J^T W r with the weights themselves at 10 bits, 4.8e-3 and
    2.8e-3 with their square roots), the cost at 16 (the cost of those weights within
    float32's precision, of the given ones within 2^-13 here)."""
    rng = np.random.default_rng(21)
    for _ in range(5):
        problem = random_scene(rng, 12, planar=planar)
        options = Options(min_invocations=0)
        nrm, frame = normalize(problem)
        if weighted:
            nrm = replace(nrm, weights=np.r_[rng.uniform(0.3, 1.0, 10), 0.0, 0.0],
                          axis_weights=nrm.axis_weights * [1.0, 0.5])
        pose = frame.to_normalized(pose_from_rvec_tvec(problem.initial_pose.rvec,
                                                       problem.initial_pose.tvec))
        spec = options.spec(12)
        values = sil_values(spec, nrm, pose, 0.0)
        got = MirrorBackend().run(spec, values)
        hess, grad, cost = _system64(values)
        # J^T W J from H_SHIFT bits shorter Jacobian magnitudes (10 of 13), J^T W r from all
        # 13 and the residuals at W_R = 13 bits of the largest (truncated: a shrink of ~2^-12),
        # compared where the circuit sums them: the rotation about the map's origin, whose
        # columns c R X take R X at W_Y = 13 bits of the map's largest binade (measured:
        # 6.0e-3 and 2.1e-3 unweighted, 1.0e-2 and 4.3e-3 weighted)
        tol_h, tol_g = (2.0 ** -6, 2.0 ** -7) if weighted else (2.0 ** -7, 2.0 ** -8)
        got_h, got_g = _about_origin(_symmetric(got["hess"]), got["grad"], values["t"])
        hess, grad = _about_origin(hess, grad, values["t"])
        assert np.linalg.norm(got_h - hess) <= tol_h * np.linalg.norm(hess)
        assert np.linalg.norm(got_g - grad) <= tol_g * np.linalg.norm(grad)
        assert abs(float(got["cost"]) - cost) <= 2.0 ** -13 * cost
        rounded = (values["wfix"] / 2.0 ** F_W) ** 2 * weight_unit(values["weights"])
        _, _, cost_rounded = _system64({**values, "weights": rounded})
        assert abs(float(got["cost"]) - cost_rounded) <= 2e-5 * cost  # float32, W_RC: 1.2e-5


def _and_gates(n: int) -> int:
    return int(np.count_nonzero(build(Spec("lm", "sil", "client", n, arith="fixed")).kind
                                == AND))


def test_a_point_costs_at_most_23_6_k_and_gates():
    """Per point of nx-sil above SHALLOW_POINTS (n = 36 to 40): 29.0 k AND with float32
    per-point costs, 1/z and x (1/z); 26.0 k with the cost in fixed point, x/z, y/z
    divided and 1/z as block fixed point (recip_block), 25.6 k with J^T W r's residuals
    at 13 bits (W_RS), 25.0 k with sqrt(w) folded into the Jacobian's factors, 24.4 k
    with the map passed as integers (map_fixed), 23.9 k with the cost's residuals at
    W_RC = 20 bits, 23.3 k with the map at W_MAP = 24 bits and R X's products at 25
    (W_XC); the rotation columns about the map's origin (c R X: 14 products, 10 of them
    truncated, for 12 exact ones; 24.4 k with all exact), each with its own block
    exponent (fixed.normalize_columns, 1.2 k) and J^T W J's magnitudes 4 bits shorter
    (H_SHIFT) 23.6 k. Up to 32 points, where
    divisions are depth-optimized (n = 4 to 8), 31.1 k then, 28.9 k before the rotation
    about the map's origin and 29.2 k now: two shallow divisions cost more than one and
    two products, for a shorter path."""
    assert (_and_gates(40) - _and_gates(36)) / 4 <= 23_600
    assert (_and_gates(8) - _and_gates(4)) / 4 <= 29_200


def test_the_cost_resolves_a_relative_change_of_1e_4():
    """The fixed-point cost (W_RC = 20 bits of the largest residual, a W_MAP = 24-bit map)
    at OpenCV's optimum of random scenes (n = 4 to 256, a quarter planar) is within 2.5e-4
    of the float64 cost (measured over 200 scenes: median 1.4e-5, 99th percentile 1.8e-4,
    largest 2.0e-4; with a 26-bit map 8.5e-6, 6.7e-5 and 1.2e-4; most of the difference
    is the map's quantization, the same at every pose), and a pose whose float64 cost is
    1e-4 higher, on either side along one direction, costs more: driver.py's cost_tol
    stays resolved."""
    rng = np.random.default_rng(5)
    rels = []
    direction = np.array([0.3, -0.2, 1.0])
    for k in range(60):
        n = int(np.round(np.exp(rng.uniform(np.log(4), np.log(256)))))
        problem = random_scene(rng, n, planar=k % 4 == 0)
        nrm, frame = normalize(problem)
        pose = frame.to_normalized(pose_from_rvec_tvec(*opencv_iterative(problem)))
        spec = Spec("lm", "sil", "client", n, arith="fixed")

        def costs(p: Pose, spec=spec, nrm=nrm) -> tuple[float, float]:
            values = sil_values(spec, nrm, p, 0.0)
            return (float(Float64Backend().run(spec, values)["cost"]),
                    float(MirrorBackend().run(spec, values)["cost"]))

        c64, cfx = costs(pose)
        rels.append(abs(cfx - c64) / c64)
        for sign in (1.0, -1.0):
            lo, hi = 0.0, 1e-2  # bisect the step raising the float64 cost by 1e-4
            for _ in range(40):
                mid = (lo + hi) / 2
                up = costs(Pose(pose.R, pose.t + sign * mid * direction))[0] >= c64 * (1 + 1e-4)
                lo, hi = (lo, mid) if up else (mid, hi)
            assert costs(Pose(pose.R, pose.t + sign * hi * direction))[1] > cfx, (k, sign)
    assert max(rels) <= 2.5e-4 and float(np.median(rels)) <= 3e-5


def test_weights_fixed_normalizes_to_the_largest():
    w = np.array([[4.0e5, 2.0e5], [0.0, 1.0e5]])
    half = round(2.0 ** (F_W - 0.5))  # sqrt(1/2) 2^F_W
    assert weights_fixed(w).tolist() == [[1 << F_W, half], [0, 1 << (F_W - 1)]]
    assert weights_fixed(np.zeros((2, 2))).tolist() == [[0, 0], [0, 0]]
    out = {"hess": np.zeros(21, np.int64), "grad": np.zeros(6, np.int64),
           "cost": np.int64(1 << 23), "ec": np.uint8(127), "er": np.uint8(127),
           "el": np.zeros(3, np.uint8)}
    # the cost's unit: 2^D_COST times the squared unit of the residuals, times the weights'
    assert float(decode(w, 0, out)["cost"]) == 2.0 ** (23 + D_COST + 2 * (127 - W_RC - 126)) * 4e5


@pytest.mark.parametrize("algorithm", ["lm", "gn"])
def test_localizing_on_it_lands_where_opencv_does(algorithm):
    rng = np.random.default_rng(5)
    for k in range(20):
        problem = random_scene(rng, int(rng.integers(4, 40)), planar=k % 3 == 0,
                               rotation_deg=(2.0, 10.0), translation_frac=0.15)
        result = localize(problem, Options(algorithm, min_invocations=0), MirrorBackend())
        assert result.spec.arith == "fixed"
        check = compare_with_opencv(problem, result.rvec, result.tvec)
        assert check["ok"], (k, check)
        assert result.converged, k


def test_the_in_circuit_solve_in_fixed_point_equals_its_mirror():
    """lm-sil-ldlt-n4-x: the sums as float32, the block LDL^T solve, the step and the cost
    scaled back by exponent arithmetic. Its step is the float64 step about as closely as the float
    circuit's (n = 4 systems are ill-conditioned), unless a point sits beyond the
    fixed-point projections' range (|a| >= 2: its J saturates, never its cost)."""
    spec = Spec("lm", "sil", "ldlt", 4, arith="fixed")
    assert spec.circuit_id == "lm-sil-ldlt-n4-x" and Spec.parse("lm-sil-ldlt-n4-x") == spec
    with pytest.raises(ValueError, match="arith 'fixed'"):
        Spec("lm", "sil", "svd", 4, arith="fixed")
    with pytest.raises(ValueError, match="arith 'fixed'"):
        Spec("lm", "do", "ldlt", 4, arith="fixed")
    circuit = build(spec)
    schedule = schedule_circuit(circuit)
    rng = np.random.default_rng(8)
    checked = 0
    for _ in range(6):
        values = random_values(spec, rng)
        values["wfix"] = weights_fixed(values["weights"])
        out = evaluate(circuit, values, schedule=schedule)
        mirror = run_mirror(spec, values)
        for name in ("step", "cost"):
            assert np.array_equal(np.asarray(out[name], np.float32).view(np.uint32),
                                  np.asarray(mirror[name], np.float32).view(np.uint32)), name
        hess, grad, cost = _system64(values)
        floats = run_mirror(replace(spec, arith="float"), values)
        v = {k: np.asarray(x, np.float64) for k, x in values.items()}
        cam = v["world"] @ v["R"].T + v["t"]
        if np.abs(cam[:, :2] / cam[:, 2:]).max() >= 2.0:
            continue
        checked += 1
        got = float(mirror["cost"]) * weight_unit(values["weights"])  # circuit_outputs
        assert abs(got - cost) <= 2e-5 * cost  # float32, W_RC: 1.2e-5
        lam = float(values["lam"])
        step = np.linalg.solve(hess + lam * np.diag(np.diag(hess)), -grad)
        tolerance = max(5 * np.linalg.norm(floats["step"] - step), 1e-2 * np.linalg.norm(step))
        # the circuit damps and solves the sums of the rotation about the map's origin, its
        # rotation entries damped by their diagonal and what they move the camera by
        # (sil.damped)
        hess_o, grad_o = _about_origin(hess, grad, v["t"])
        weight = np.diag(hess_o).copy()
        weight[3:] += (hat(v["t"]) ** 2).T @ np.diag(hess_o)[:3]
        step_o = np.linalg.solve(hess_o + lam * np.diag(weight), -grad_o)
        assert np.linalg.norm(step_about_camera(mirror["step"], v["t"])
                              - step_about_camera(step_o, v["t"])) <= tolerance
    assert checked >= 3
