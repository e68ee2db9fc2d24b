"""float32 circuits bit for bit against the flush-to-zero mirror, and the mirror
against plain numpy float32 wherever inputs and result are normal or zero."""

import numpy as np
import pytest
from arith_harness import Compiled
from hypothesis import given, settings
from hypothesis import strategies as st

from snail_bench.ops import ops_report
from snail_common.arith import fadd, fcmp, fconst, fconvert, fdiv, fmul, fsqrt
from snail_common.arith import mirror as MR

F = "float32"
RNG = np.random.default_rng(2024)
MAXF = np.finfo(np.float32).max
TINY = np.float32(2.0 ** -126)
ULP1 = np.float32(2.0 ** -23)
PI = float(np.float32(np.pi))

BINARY = {
    "add": (fadd.fadd, MR.add),
    "add_depth_opt": (lambda b, x, y: fadd.fadd(b, x, y, depth_opt=True), MR.add),
    "sub": (fadd.fsub, MR.sub),
    "sub_depth_opt": (lambda b, x, y: fadd.fsub(b, x, y, depth_opt=True), MR.sub),
    "mul": (fmul.fmul, MR.mul),
    "div": (fdiv.fdiv, MR.div),
    "div_depth_opt": (lambda b, x, y: fdiv.fdiv(b, x, y, depth_opt=True), MR.div),
    "lt": (fcmp.lt, MR.lt),
    "lt_depth_opt": (lambda b, x, y: fcmp.lt(b, x, y, depth_opt=True), MR.lt),
    "le": (fcmp.le, MR.le),
    "le_depth_opt": (lambda b, x, y: fcmp.le(b, x, y, depth_opt=True), MR.le),
    "gt": (fcmp.gt, lambda x, y: MR.lt(y, x)),
    "ge": (fcmp.ge, lambda x, y: MR.le(y, x)),
    "eq": (fcmp.eq, MR.eq),
    "min": (fcmp.fmin, MR.minimum),
    "max": (fcmp.fmax, MR.maximum),
}
UNARY = {
    "sqrt": (fsqrt.fsqrt, MR.sqrt),
    "sqrt_depth_opt": (lambda b, x: fsqrt.fsqrt(b, x, depth_opt=True), MR.sqrt),
    "neg": (fcmp.fneg, MR.neg),
    "abs": (fcmp.fabs, MR.absolute),
    "mul_pi": (lambda b, x: fmul.fmul_const(b, x, PI), lambda x: MR.mul_const(x, PI)),
    "mul_0.1": (lambda b, x: fmul.fmul_const(b, x, 0.1), lambda x: MR.mul_const(x, 0.1)),
    "mul_-3": (lambda b, x: fmul.fmul_const(b, x, -3.0), lambda x: MR.mul_const(x, -3.0)),
    "mul_2^-100": (lambda b, x: fmul.fmul_const(b, x, 2.0 ** -100),
                   lambda x: MR.mul_const(x, 2.0 ** -100)),
    "mul_1e30": (lambda b, x: fmul.fmul_const(b, x, 1e30), lambda x: MR.mul_const(x, 1e30)),
    "mul_0": (lambda b, x: fmul.fmul_const(b, x, -0.0), lambda x: MR.mul_const(x, -0.0)),
}
PREDICATES = {"lt", "le", "gt", "ge", "eq", "lt_depth_opt", "le_depth_opt"}


@pytest.fixture(scope="module")
def circ():
    cache = {}

    def get(name):
        if name not in cache:
            if name in BINARY:
                fn = BINARY[name][0]
                out = "bool" if name in PREDICATES else F
                cache[name] = Compiled(fn, {"x": (32, F), "y": (32, F)}, out)
            else:
                cache[name] = Compiled(UNARY[name][0], {"x": (32, F)}, F)
        return cache[name]
    return get


def f32(v) -> np.ndarray:
    return np.asarray(v, np.float32)


def assert_same(got, want, *inputs):
    """Bit equality (any NaN matches any NaN; booleans compare as booleans)."""
    got, want = np.asarray(got), np.asarray(want)
    if got.dtype == bool or want.dtype == bool:
        bad = got != want
    else:
        bad = (MR.bits(got) != MR.bits(want)) & ~(np.isnan(got) & np.isnan(want))
    idx = np.flatnonzero(bad)
    if idx.size:
        rows = [tuple(f"{float(a[i])!r}/{int(MR.bits(a[i])):#010x}" for a in inputs)
                + (got[i], want[i]) for i in idx[:5]]
        raise AssertionError(f"{idx.size} mismatches, e.g. {rows}")


def run_binary(circ, name, x, y):
    x, y = f32(x), f32(y)
    got = circ(name)(x, y)
    assert_same(got, BINARY[name][1](x, y), x, y)
    return got


def run_unary(circ, name, x):
    x = f32(x)
    got = circ(name)(x)
    assert_same(got, UNARY[name][1](x), x)
    return got


# ---- input generators ------------------------------------------------------------------
def random_bits(n: int) -> np.ndarray:
    return RNG.integers(0, 2 ** 32, n, dtype=np.uint64).astype(np.uint32)


def finite(n: int) -> np.ndarray:
    u = random_bits(n)
    u = np.where((u & 0x7F800000) == 0x7F800000, u & 0xBFFFFFFF, u)   # no inf/NaN
    return MR.from_bits(u)


def near(x: np.ndarray, spread: int) -> np.ndarray:
    """Random values whose exponent is within ``spread`` of x's (and random sign)."""
    u = random_bits(len(x))
    e = ((MR.bits(x) >> 23) & 0xFF).astype(np.int64) + RNG.integers(-spread, spread + 1, len(x))
    e = np.clip(e, 0, 254).astype(np.uint32)
    return MR.from_bits((u & 0x807FFFFF) | (e << 23))


def with_exponent_sum(x: np.ndarray, target: int, spread: int) -> np.ndarray:
    """Values y with ex + ey close to ``target`` (products near the edges)."""
    u = random_bits(len(x))
    ex = ((MR.bits(x) >> 23) & 0xFF).astype(np.int64)
    e = np.clip(target - ex + RNG.integers(-spread, spread + 1, len(x)), 1, 254)
    return MR.from_bits((u & 0x807FFFFF) | (e.astype(np.uint32) << 23))


def cancelling(x: np.ndarray) -> np.ndarray:
    """-x with its exponent moved by 0 or 1 and up to 24 low bits flipped: massive
    cancellation in x + y (the near path), including exact zeros."""
    u = MR.bits(x) ^ np.uint32(0x80000000)
    low = RNG.integers(0, 25, len(x))
    u = u ^ (random_bits(len(x)) & ((np.uint64(1) << low.astype(np.uint64)) - np.uint64(1))
             .astype(np.uint32))
    e = ((u >> 23) & 0xFF).astype(np.int64) + RNG.integers(-1, 2, len(x))
    e = np.clip(e, 1, 254).astype(np.uint32)
    return MR.from_bits((u & 0x807FFFFF) | (e << 23))


def binary_batch(name: str, n: int = 6000) -> tuple[np.ndarray, np.ndarray]:
    x = finite(n)
    parts_y = [finite(n // 3), near(x[n // 3 : 2 * n // 3], 3), near(x[2 * n // 3 :], 30)]
    y = np.concatenate(parts_y)
    k = n // 4
    if name.startswith(("add", "sub")):  # half the batch cancels heavily
        y[: n // 2] = cancelling(x[: n // 2])
        if name.startswith("sub"):
            y[: n // 2] = -y[: n // 2]
    if name == "mul":  # exponents summing to products near overflow / near 2^-126
        y[:k] = with_exponent_sum(x[:k], 254 + 127, 3)
        y[k : 2 * k] = with_exponent_sum(x[k : 2 * k], 1 + 127, 3)
    if name.startswith("div"):  # ey near ex - 127 (huge quotients) or ex + 126 (tiny ones)
        ex = ((MR.bits(x) >> 23) & 0xFF).astype(np.int64)
        for sl, off in ((slice(0, k), -127), (slice(k, 2 * k), 126)):
            e = np.clip(ex[sl] + off + RNG.integers(-2, 3, k), 1, 254).astype(np.uint32)
            y[sl] = MR.from_bits((MR.bits(y[sl]) & 0x807FFFFF) | (e << 23))
    return x, y


# ---- random batches --------------------------------------------------------------------
@pytest.mark.parametrize("name", list(BINARY))
def test_binary_op_random_batch(circ, name):
    x, y = binary_batch(name)
    run_binary(circ, name, x, y)
    if name not in PREDICATES:
        run_binary(circ, name, y, x)


@pytest.mark.parametrize("name", list(UNARY))
def test_unary_op_random_batch(circ, name):
    x = np.concatenate([finite(4000), MR.from_bits(random_bits(500) & 0x807FFFFF)])
    run_unary(circ, name, x)


normal32 = st.floats(width=32, allow_nan=False, allow_infinity=False).filter(
    lambda v: v == 0 or abs(v) >= 2.0 ** -126)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(normal32, normal32), min_size=1, max_size=64),
       st.sampled_from([n for n in BINARY if "depth" not in n]))
def test_binary_ops_hypothesis(circ, pairs, name):
    x = f32([p[0] for p in pairs])
    y = f32([p[1] for p in pairs])
    run_binary(circ, name, x, y)


@settings(max_examples=15, deadline=None)
@given(st.lists(normal32, min_size=1, max_size=64),
       st.sampled_from([n for n in UNARY if "depth" not in n]))
def test_unary_ops_hypothesis(circ, xs, name):
    run_unary(circ, name, f32(xs))


# ---- explicit edge cases ---------------------------------------------------------------
def test_add_edge_cases(circ):
    one = np.float32(1)
    cases = [
        (one, np.float32(2.0 ** -24)),                 # tie, LSB even -> stays 1
        (one + ULP1, np.float32(2.0 ** -24)),          # tie, LSB odd -> rounds up
        (one, np.float32(2.0 ** -24) * np.float32(1.5)),
        (np.float32(2) - ULP1 * 2, np.float32(2) - ULP1 * 2),   # carry out of the mantissa
        (np.float32(16777215), one),                   # 2^24 - 1 + 1 -> 2^24
        (np.float32(16777215), np.float32(0.5)),       # tie at 2^24 boundary
        (np.float32(3.5), np.float32(-3.5)),           # exact cancellation -> +0
        (np.float32(-3.5), np.float32(3.5)),
        (np.float32(-0.0), np.float32(-0.0)),          # -0 + -0 = -0
        (np.float32(0.0), np.float32(-0.0)),
        (MAXF, MAXF),                                   # overflow -> inf
        (-MAXF, -MAXF),
        (MAXF, np.float32(2.0 ** 103)),                # exactly half an ulp: tie -> inf? even
        (MAXF, np.float32(2.0 ** 102)),
        (TINY * np.float32(1.5), -TINY),               # 2^-127 -> flush to +0
        (-TINY * np.float32(1.5), TINY),               # -> -0
        (TINY * np.float32(2), -TINY),                 # exactly 2^-126 stays
        (MR.from_bits(np.uint32(0x00400000)), one),    # subnormal input reads as 0
        (MR.from_bits(np.uint32(0x80000001)), np.float32(0.0)),   # -sub + 0 = +0
        (MR.from_bits(np.uint32(0x80000001)), np.float32(-0.0)),  # -sub + -0 = -0
        (one, np.float32(-1 + 2.0 ** -24)),            # massive cancellation
        (np.float32(2.0 ** 100), np.float32(2.0 ** -100)),
        (np.float32(1 / 3), np.float32(2 / 3)),
    ]
    x, y = f32([c[0] for c in cases]), f32([c[1] for c in cases])
    for add, sub in (("add", "sub"), ("add_depth_opt", "sub_depth_opt")):
        got = run_binary(circ, add, x, y)
        assert MR.bits(got[6]) == 0 and MR.bits(got[7]) == 0        # +0
        assert MR.bits(got[8]) == 0x80000000
        assert np.isposinf(got[10]) and np.isneginf(got[11])
        assert MR.bits(got[14]) == 0 and MR.bits(got[15]) == 0x80000000
        run_binary(circ, sub, x, x)                               # x - x = +0
        assert np.all(MR.bits(circ(sub)(x, x))[np.abs(x) >= TINY] == 0)
        run_binary(circ, sub, x, -y)


def test_add_near_and_far_paths(circ):
    """Each normalization case of the adder: carry out (shift 0), plain (1), one bit of
    cancellation with a sticky borrow (far path, shift 2), and deep cancellation with
    the operands one exponent apart (near path) down to exact zero."""
    one, ulp = np.float32(1), ULP1
    cases = [
        (np.float32(1.5), np.float32(1.75)),               # carry out
        (one, np.float32(2.0 ** -30)),                     # far add, all sticky
        (one, np.float32(-(2.0 ** -30))),                  # 1 - tiny: 0.111..1 -> rounds to 1
        (one, np.float32(-3 * 2.0 ** -26)),                # far sub, shift 2, round bit set
        (one + ulp, np.float32(-(2.0 ** -25) * 1.5)),      # far sub, borrow through sticky
        (np.float32(2), -(np.float32(2) - ulp)),           # d = 1, result 2^-22
        (one, -(one - np.float32(2.0 ** -24))),            # d = 1, result 2^-24
        (np.float32(1.5), np.float32(-0.75) - ulp),        # d = 1, no cancellation, tie
        (one + 3 * ulp, -(one + ulp)),                     # d = 0
        (np.float32(3.0), np.float32(-3.0)),               # exact zero
        (TINY * np.float32(3), -TINY * np.float32(2.5)),   # near path below 2^-126: flush
    ]
    x, y = f32([c[0] for c in cases]), f32([c[1] for c in cases])
    for name in ("add", "add_depth_opt"):
        got = run_binary(circ, name, x, y)
        run_binary(circ, name, y, x)
        assert got[2] == one and got[6] == np.float32(2.0 ** -24)
        assert MR.bits(got[9]) == 0 and MR.bits(got[10]) == 0


@settings(max_examples=20, deadline=None)
@given(st.lists(st.tuples(st.integers(0x00800000, 0x7F7FFFFF), st.integers(-1, 1),
                          st.integers(0, (1 << 24) - 1), st.booleans()),
                min_size=1, max_size=64))
def test_add_cancellation_hypothesis(circ, rows):
    """x + y with y close to -x (same or next exponent): the leading-zero path."""
    u = np.array([r[0] for r in rows], np.int64)
    e = np.clip(((u >> 23) & 0xFF) + np.array([r[1] for r in rows]), 1, 254)
    v = ((u & 0x7FFFFF) ^ np.array([r[2] for r in rows]) & 0x7FFFFF) | (e << 23)
    sign = np.array([r[3] for r in rows], np.int64) << 31
    x = MR.from_bits((u | sign).astype(np.uint32))
    y = MR.from_bits((v | (sign ^ (1 << 31))).astype(np.uint32))
    run_binary(circ, "add", x, y)
    run_binary(circ, "sub", x, -y)


def test_mul_edge_cases(circ):
    cases = [
        (1 / 3, 3.0), (2.0 ** 64, 2.0 ** 64), (MAXF, 2.0), (MAXF, -1.0000001),
        (2.0 ** -63, 2.0 ** -63),                      # exactly 2^-126
        (2.0 ** -64, 2.0 ** -63),                      # 2^-127 -> flushed
        (-(2.0 - 2.0 ** -23) * 2.0 ** -64, 2.0 ** -63),  # all-ones just below 2^-126 -> -2^-126
        ((2.0 - 2.0 ** -22) * 2.0 ** -64, 2.0 ** -63),   # not all ones -> +0
        (1 + 2.0 ** -23, 1 + 2.0 ** -23),              # rounding with sticky
        (1 + 2.0 ** -12, 1 + 2.0 ** -12),              # 1 + 2^-11 + 2^-24: tie -> even
        (1.5, 1 + 2.0 ** -23),                          # tie
        (0.0, -5.0), (-0.0, -0.0), (3.0, float(MR.from_bits(np.uint32(0x00000005)))),
        (16777215.0, 16777215.0), (-7.0, 0.1),
    ]
    x, y = f32([c[0] for c in cases]), f32([c[1] for c in cases])
    got = run_binary(circ, "mul", x, y)
    assert got[4] == TINY and MR.bits(got[5]) == 0 and got[6] == -TINY
    assert np.isposinf(got[1])
    assert np.isposinf(got[2]) and np.isneginf(got[3])
    assert MR.bits(got[12]) == 0 and MR.bits(got[13]) == 0


def test_div_edge_cases(circ):
    cases = [
        (1.0, 3.0), (2.0, 3.0), (10.0, 10.0), (-7.0, 2.0), (1.0, 0.0), (-1.0, 0.0),
        (0.0, 0.0), (0.0, -3.0), (-0.0, 3.0), (MAXF, 0.5), (TINY, 2.0), (TINY, 0.5),
        (1.0, MAXF), (16777215.0, 16777216.0), (1.0, 1.0 - 2.0 ** -24), (3.0, 1.5),
        (2.0 ** -126, 1 + 2.0 ** -23),                 # just below 2^-126
        ((2.0 - 2.0 ** -23), 4.0 * 2.0 ** 125),        # all ones just below 2^-126
    ]
    x, y = f32([c[0] for c in cases]), f32([c[1] for c in cases])
    for name in ("div", "div_depth_opt"):
        got = run_binary(circ, name, x, y)
        assert got[0] == np.float32(1 / 3) and got[2] == 1
        assert np.isposinf(got[4]) and np.isneginf(got[5]) and np.isnan(got[6])
        assert np.isposinf(got[9]) and MR.bits(got[10]) == 0


def test_sqrt_edge_cases(circ):
    squares = f32([4, 9, 2.25, 16777216.0, 144, 0.25, 1, 6.25e-2, 2.0 ** -100])
    others = f32([2, 3, 0.0, -0.0, -1.0, MAXF, TINY, 1 - 2.0 ** -24, 1 + 2.0 ** -23,
                  MR.from_bits(np.uint32(0x80000003))])
    for name in ("sqrt", "sqrt_depth_opt"):
        got = run_unary(circ, name, squares)
        assert np.all(got * got == squares)
        got = run_unary(circ, name, others)
        assert MR.bits(got[2]) == 0 and MR.bits(got[3]) == 0x80000000 and np.isnan(got[4])
        assert MR.bits(got[9]) == 0x80000000


def test_compare_edge_cases(circ):
    sub = MR.from_bits(np.uint32(0x00000010))
    nsub = MR.from_bits(np.uint32(0x80000010))
    vals = f32([0.0, -0.0, sub, nsub, TINY, -TINY, 1.0, -1.0, 1 + 2.0 ** -23, MAXF, -MAXF,
                np.inf, -np.inf, 2.0, 3.0])
    x, y = np.meshgrid(vals, vals)
    x, y = x.ravel(), y.ravel()
    for name in ("lt", "le", "gt", "ge", "eq", "min", "max", "lt_depth_opt", "le_depth_opt"):
        run_binary(circ, name, x, y)
    eq = circ("eq")(x, y)
    assert eq[(x == 0) & (y == 0)].all()                # +0, -0 and subnormals all equal


def test_specials_are_as_documented(circ):
    inf, nan = np.float32(np.inf), np.float32(np.nan)
    big = np.float32(3e38)
    add = circ("add")(f32([inf, inf, -inf, 1.0, inf, -big]), f32([1.0, -inf, 5.0, nan, -big, inf]))
    assert np.isposinf(add[0]) and np.isposinf(add[1]) and np.isneginf(add[2])
    assert np.isinf(add[3]) and np.isposinf(add[4]) and np.isposinf(add[5])
    mul = circ("mul")(f32([inf, inf, 2.0, 1e-30, nan]), f32([2.0, 0.0, -inf, -inf, 1.0]))
    assert np.isposinf(mul[0]) and np.isnan(mul[1]) and np.isneginf(mul[2])
    assert np.isneginf(mul[3]) and np.isinf(mul[4])
    for name in ("div", "div_depth_opt"):
        div = circ(name)(f32([inf, 1.0, inf, 3e38, -0.0, 5.0]),
                         f32([1e-30, inf, -inf, -inf, 0.0, -0.0]))
        assert np.isposinf(div[0]) and MR.bits(div[1]) == 0 and np.isnan(div[2])
        assert MR.bits(div[3]) == 0x80000000 and np.isnan(div[4]) and np.isneginf(div[5])
    sq = circ("sqrt")(f32([inf, -4.0]))
    assert np.isposinf(sq[0]) and np.isnan(sq[1])


def test_mirror_equals_numpy_on_normal_values():
    x, y = finite(20000), finite(20000)
    y[:10000] = near(x[:10000], 2)
    normal = lambda v: (np.abs(v) >= TINY) | (v == 0)  # noqa: E731
    with np.errstate(all="ignore"):
        for mine, ref in ((MR.add, np.add), (MR.sub, np.subtract), (MR.mul, np.multiply),
                          (MR.div, np.divide)):
            want = ref(x, y)
            ok = normal(x) & normal(y) & normal(want) & ~np.isnan(want)
            assert np.array_equal(MR.bits(mine(x, y)[ok]), MR.bits(want[ok]))
        want = np.sqrt(x)
        ok = normal(x) & ~np.isnan(want)
        assert np.array_equal(MR.bits(MR.sqrt(x)[ok]), MR.bits(want[ok]))
        ok = normal(x) & normal(y)
        assert np.array_equal(MR.lt(x, y)[ok], (x < y)[ok])
        assert np.array_equal(MR.eq(x, y)[ok], (x == y)[ok])
    assert MR.bits(MR.add(np.float32(TINY * 1.5), -TINY)) == 0        # the flush itself


# ---- conversions, constants ------------------------------------------------------------
def test_int_to_float():
    c = Compiled(fconvert.i2f, {"x": (32, "int32")}, F)
    v = RNG.integers(-2 ** 31, 2 ** 31, 5000, dtype=np.int64) >> RNG.integers(0, 32, 5000)
    edges = [0, 1, -1, 2 ** 31 - 1, -2 ** 31, 2 ** 24 + 1, 2 ** 24 + 3, -(2 ** 25 + 2),
             2 ** 25 + 6, 16777217, 123456789]
    v = np.concatenate([np.array(edges), v]).astype(np.int32)
    assert_same(c(v), MR.i2f(v), v)


def test_float_to_int():
    c = Compiled(fconvert.f2i, {"x": (32, F)}, "int32")
    u = random_bits(5000)
    u = (u & 0x807FFFFF) | (RNG.integers(90, 175, 5000).astype(np.uint32) << 23)
    edges = f32([0.0, -0.0, 0.5, -0.99, 1.0, -1.5, 2.0 ** 31, -2.0 ** 31, 2.0 ** 31 - 128,
                 -(2.0 ** 31 - 128), 1e10, np.inf, -np.inf, np.nan, 8388607.5])
    x = np.concatenate([edges, MR.from_bits(u)])
    got = c(x)
    assert np.array_equal(got, MR.f2i(x))
    assert got[7] == -2 ** 31 and got[6] == -2 ** 31 and got[4] == 1 and got[5] == -1


def test_constants_are_free_and_exact():
    for v in (0.0, -0.0, 1.0, PI, -1e-30, 3.4e38):
        c = Compiled(lambda b, x, v=v: fadd.fadd(b, x, fconst.fconst(v)), {"x": (32, F)}, F)
        x = finite(200)
        assert_same(c(x), MR.add(x, np.float32(v)), x)
    w = fconst.fconst(1.5, (2, 3))
    assert w.shape == (2, 3, 32) and set(np.unique(w)) <= {0, 1}


def test_ops_broadcast_over_leading_shapes():
    from snail_common.circuit import CircuitBuilder, evaluate
    b = CircuitBuilder()
    x = b.input("x", (3, 2), 32, F)
    y = b.input("y", (2,), 32, F)
    b.output("s", fadd.fadd(b, x, y), F)
    b.output("p", fmul.fmul(b, x, fconst.fconst(2.5)), F)
    c = b.build()
    xs, ys = finite(6).reshape(3, 2), finite(2)
    out = evaluate(c, {"x": xs, "y": ys})
    assert_same(out["s"].ravel(), MR.add(xs, ys).ravel(), xs.ravel())
    assert_same(out["p"].ravel(), MR.mul(xs, np.float32(2.5)).ravel(), xs.ravel())


# ---- budgets ---------------------------------------------------------------------------
BUDGETS = {"add": 400, "sub": 400, "mul": 1000, "div": 900, "sqrt": 800, "lt": 40, "le": 40,
           "eq": 40}
# measured counts of ops over budget: a ceiling so they cannot silently regress
OVER_BUDGET = {"add": 528, "sub": 528, "lt": 41, "le": 41}


@pytest.fixture(scope="module")
def report():
    return ops_report()["ops"]


@pytest.mark.parametrize("name", [
    pytest.param(n, marks=pytest.mark.xfail(strict=True, reason=f"{OVER_BUDGET[n]} ANDs"))
    if n in OVER_BUDGET else n for n in BUDGETS])
def test_and_budget(report, name):
    assert report[name]["and"] <= BUDGETS[name]


@pytest.mark.parametrize("name", list(OVER_BUDGET))
def test_over_budget_ops_do_not_regress(report, name):
    assert report[name]["and"] <= OVER_BUDGET[name]


def test_report_shape_and_tradeoffs(report):
    assert set(report) >= {"add", "sub", "mul", "div", "div_depth_opt", "sqrt",
                           "sqrt_depth_opt", "lt", "le", "eq", "min", "max", "i2f", "f2i",
                           "mul_const"}
    assert all(set(v) == {"and", "xor", "depth"} for v in report.values())
    assert report["mul_const"]["and"] < report["mul"]["and"]
    for op in ("div", "sqrt", "add", "sub", "lt", "le"):
        assert report[f"{op}_depth_opt"]["depth"] * 2 < report[op]["depth"]
