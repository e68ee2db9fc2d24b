"""The block LDL^T solve of the fixed-point in-circuit family (block_ldlt.py): its circuit
equals its mirror bit for bit, it solves damped normal systems to the precision of its
narrow format from no damping up to lambda_max, float_system hands it entries of at most
1, and its chain is short enough for lm-sil-ldlt-n6-x to meet issue 16's budget."""

from __future__ import annotations

import numpy as np
import pytest
from test_loc_circuits import random_values

from snail_common.circuit import CircuitBuilder
from snail_common.circuit.cleartext import evaluate
from snail_common.circuit.schedule import schedule_circuit
from snail_common.loc.driver import LAMBDA_MAX, LAMBDA_MIN
from snail_common.pnp.block_ldlt import SOLVE_FRAC, block_ldlt_solve
from snail_common.pnp.fops import CircuitBackend, F, MirrorBackend
from snail_common.pnp.normal import UPPER
from snail_common.pnp.normal_fixed import float_system, weights_fixed
from snail_common.pnp.sil import _fixed_sums, damped
from snail_common.pnp.spec import Spec, build, input_shapes, run_mirror

LAMS = [0.0, 1e-3, 1.0, LAMBDA_MAX]


def _system(rng: np.random.Generator, lam: float, spread: float) -> tuple[np.ndarray, ...]:
    """A damped normal matrix (float64, entries at most 1 before damping, as float_system
    gives them, the largest anywhere from 2^-20 to 1; column norms spread over 2^spread)
    and a right-hand side."""
    jac = rng.normal(size=(12, 6)) * 2.0 ** rng.uniform(-spread, 0, 6)
    hess = jac.T @ jac
    hess *= 2.0 ** rng.uniform(-20, 0) / np.abs(hess).max()
    hess += lam * np.diag(np.diag(hess))
    return hess, rng.normal(size=6) * 2.0 ** rng.uniform(-8, 0)


def _packed(hess: np.ndarray) -> np.ndarray:
    return np.array([hess[e] for e in UPPER], np.float32)


def test_solves_damped_systems_from_no_damping_to_lambda_max():
    rng = np.random.default_rng(4)
    be = MirrorBackend()
    for lam in LAMS:
        for _ in range(20):
            hess, rhs = _system(rng, lam, spread=4.0)
            x = block_ldlt_solve(F(be, _packed(hess)), F(be, rhs.astype(np.float32))).v
            want = np.linalg.solve(hess, rhs)
            assert np.all(np.isfinite(x)), lam
            bound = 2.0 ** (4 - SOLVE_FRAC) * np.linalg.cond(hess) * np.linalg.norm(want)
            assert np.linalg.norm(x - want) <= bound, lam


def test_circuit_equals_mirror_bit_for_bit():
    b = CircuitBuilder()
    be = CircuitBackend(b)
    h = F(be, b.input("h", (21,), bits=32, dtype="float32"))
    g = F(be, b.input("g", (6,), bits=32, dtype="float32"))
    with be.shallow():
        b.output("x", block_ldlt_solve(h, g).v, dtype="float32")
    circuit = b.build()
    rng = np.random.default_rng(5)
    for lam in LAMS:
        hess, rhs = _system(rng, lam, spread=8.0)
        values = {"h": _packed(hess), "g": rhs.astype(np.float32)}
        got = np.asarray(evaluate(circuit, values)["x"], np.float32)
        want = block_ldlt_solve(F(MirrorBackend(), values["h"]), F(MirrorBackend(), values["g"])).v
        assert np.array_equal(got.view(np.uint32), want.view(np.uint32)), lam


def test_float_system_gives_the_solve_entries_of_at_most_one():
    """The block solve's determinants are cubic: at lambda_max they stay finite only
    because float_system scales the integer sums to at most 1."""
    spec = Spec("lm", "sil", "ldlt", 64, arith="fixed")
    rng = np.random.default_rng(6)
    be = MirrorBackend()
    for _ in range(4):
        values = random_values(spec, rng)
        values["wfix"] = weights_fixed(values["weights"])
        inputs = {k: F(be, np.asarray(values[k], np.int64 if k == "wfix" else np.float32)
                       .reshape(shape))
                  for k, shape in input_shapes("lm", 64, "ldlt", "fixed").items()}
        hess, grad, _, _ = float_system(inputs["R"], *_fixed_sums(inputs))
        assert 0 < np.abs(hess.v).max() <= 1
        step = block_ldlt_solve(damped(hess, F(be, np.float32(LAMBDA_MAX))), -grad).v
        assert np.all(np.isfinite(step)) and np.any(step != 0)


@pytest.fixture(scope="module")
def n6():
    spec = Spec("lm", "sil", "ldlt", 6, arith="fixed")
    return spec, build(spec)


def test_the_in_circuit_family_meets_the_issue_budget(n6):
    """Issue 16: at n = 6 at most 0.45 M AND and AND-depth 2,500 (LDL^T: 0.449 M, 3,455)."""
    _, circuit = n6
    assert circuit.counts()["and"] <= 450_000
    assert circuit.depth() <= 2_500


def test_the_whole_circuit_equals_its_mirror_from_lambda_min_to_max(n6):
    spec, circuit = n6
    rng = np.random.default_rng(9)
    cases = [random_values(spec, rng) for _ in range(12)]
    for case, lam in zip(cases, [LAMBDA_MIN, LAMBDA_MAX, *(c["lam"] for c in cases[2:])]):
        case["lam"] = np.float32(lam)
        case["wfix"] = weights_fixed(case["weights"])
    batch = {k: np.stack([c[k] for c in cases]) for k in cases[0]}
    out = evaluate(circuit, batch, schedule=schedule_circuit(circuit), batch=len(cases))
    for i, case in enumerate(cases):
        mirror = run_mirror(spec, case)
        assert np.all(np.isfinite(mirror["step"])), i
        for name in ("step", "cost"):
            got = np.asarray(out[name][i], np.float32)
            assert np.array_equal(got.view(np.uint32), mirror[name].view(np.uint32)), (i, name)
