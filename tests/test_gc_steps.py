"""Step count is time: a schedule may take at most about 2 steps per AND level.

At small sizes every step costs the engine a fixed ~15-25 us of Python whatever its width,
so XOR logic must fold into one linear step between two AND steps. Measured on the circuits
that matter: ripple adders, every float32 op, a chain of dependent float ops shaped like a
6x6 LDL^T factorization, and the shared Bristol files.
"""

import numpy as np
import pytest
from shared_paths import BRISTOL

from snail_common.arith import fadd, fdiv, fmul, integer
from snail_common.arith.catalog import OPS
from snail_common.circuit import (
    CircuitBuilder,
    decode_outputs,
    encode_inputs,
    evaluate_bits,
    schedule_circuit,
)
from snail_common.circuit.bristol import load_bristol
from snail_common.gc import garbled_run

# one linear step before the first AND level, then (AND, linear) per level: 2 * depth + 1
SLACK = 2
N = 6

# Circuits over the bound today, with steps - 2 * depth measured at MAX_TERMS = 16 and
# MAX_TERMS_SHARED = 4. Cause: a shared XOR wire with more than 4 leaves (16 unshared) is cut
# into its own linear sub-step, so long XOR chains inside one AND layer (multiplier partial
# sums, the carry-save trees of fmul/fdiv/fsqrt) take several linear steps per level. With
# cut thresholds of 64/64 every circuit here but mult64/mult2_64 is within the bound; those
# two need unbounded expansion (2x-4x the XOR terms, still far cheaper than the steps).
OVER = {
    "mul": 79, "mul_const": 38, "div": 26, "div_depth_opt": 27, "sqrt": 25,
    "sqrt_depth_opt": 25, "i2f": 3, "ldlt6": 984, "FP-add": 67, "FP-ceil": 11,
    "FP-floor": 11, "FP-i2f": 9, "FP-mul": 42, "mult64": 366, "mult2_64": 704,
}


def ripple_add(bits: int):
    b = CircuitBuilder()
    x, y = (b.input(n, (4,), bits, f"uint{bits}") for n in "xy")
    b.output("s", integer.add(b, x, y), f"uint{bits}")
    return b.build()


def float_op(name: str):
    fn, n_args, in_dtype, out_dtype = OPS[name]
    b = CircuitBuilder()
    out = fn(b, *(b.input(f"x{i}", (), 32, in_dtype) for i in range(n_args)))
    b.output("r", out[None] if out_dtype == "bool" else out, out_dtype)
    return b.build()


def ldlt_chain():
    """D and L of A = L D L^T (unit lower L) for a symmetric 6x6 A, in the textbook order:
    a long chain of dependent fmul/fsub/fdiv (depth-optimized division)."""
    b = CircuitBuilder()
    a = b.input("a", (N, N), 32, "float32")
    d, lo = {}, {}
    for j in range(N):
        s = a[j, j]
        for k in range(j):
            s = fadd.fsub(b, s, fmul.fmul(b, fmul.fmul(b, lo[j, k], lo[j, k]), d[k]))
        d[j] = s
        for i in range(j + 1, N):
            t = a[i, j]
            for k in range(j):
                t = fadd.fsub(b, t, fmul.fmul(b, fmul.fmul(b, lo[i, k], lo[j, k]), d[k]))
            lo[i, j] = fdiv.fdiv(b, t, d[j], depth_opt=True)
    b.output("d", np.stack([d[j] for j in range(N)]), "float32")
    b.output("l", np.stack([lo[i, j] for i in range(N) for j in range(i)]), "float32")
    return b.build()


BRISTOL_FILES = sorted(p for p in BRISTOL.glob("*.txt") if not p.name.startswith("LICENSE"))
CIRCUITS = {
    **{f"ripple_add{n}": (lambda n=n: ripple_add(n)) for n in (8, 32, 64)},
    **{name: (lambda name=name: float_op(name)) for name in OPS},
    "ldlt6": ldlt_chain,
    **{p.stem: (lambda p=p: load_bristol(p)) for p in BRISTOL_FILES},
}


@pytest.fixture(scope="module")
def compiled():
    cache = {}

    def get(name):
        if name not in cache:
            c = CIRCUITS[name]()
            cache[name] = (c, schedule_circuit(c))
        return cache[name]
    return get


def test_the_circuits_that_matter_are_measured():
    assert {"ripple_add64", "add", "mul", "div_depth_opt", "ldlt6", "FP-mul"} <= set(CIRCUITS)
    assert len(BRISTOL_FILES) >= 16
    assert set(OVER) <= set(CIRCUITS)


@pytest.mark.parametrize("name", [
    pytest.param(n, marks=pytest.mark.xfail(
        strict=True, reason=f"{OVER[n]} steps over 2 * depth (schedule cut thresholds)"))
    if n in OVER else n for n in CIRCUITS])
def test_at_most_two_steps_per_and_level(compiled, name):
    circuit, schedule = compiled(name)
    depth = circuit.depth()
    assert depth > 0
    assert schedule.n_steps <= 2 * depth + SLACK, (
        f"{name}: {schedule.n_steps} steps for AND-depth {depth} "
        f"({schedule.n_steps / depth:.2f} per level)")


@pytest.mark.parametrize("name", sorted(OVER))
def test_over_bound_circuits_do_not_regress(compiled, name):
    circuit, schedule = compiled(name)
    assert schedule.n_steps - 2 * circuit.depth() <= OVER[name]


def test_ldlt_chain_garbled_matches_cleartext(compiled):
    """The deep, narrow chain (thousands of small steps) through the real engine."""
    circuit, schedule = compiled("ldlt6")
    m = np.random.default_rng(6).standard_normal((N, N))
    a = (m @ m.T + N * np.eye(N)).astype(np.float32)
    bits = encode_inputs(circuit, {"a": a})[0]
    got = garbled_run(schedule, bits)
    assert np.array_equal(got, evaluate_bits(schedule, bits[None])[0])
    d = decode_outputs(circuit, got[None])["d"]
    lower = np.linalg.cholesky(a.astype(np.float64))
    assert np.allclose(d, np.diag(lower) ** 2, rtol=1e-4)
