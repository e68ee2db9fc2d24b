"""SVD solver and pseudo-inverse GN step: the float32 mirror solves what float64 numpy
solves, survives rank deficiency, and the circuit's cleartext evaluation is bit-identical."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from snail_common.circuit import CircuitBuilder
from snail_common.circuit.cleartext import evaluate
from snail_common.pnp.do import normal_equations64
from snail_common.pnp.fops import CircuitBackend, F, MirrorBackend
from snail_common.pnp.normal import UPPER, normal_equations
from snail_common.pnp.svd import pinv_step, svd_solve, weighted_system

MIRROR = MirrorBackend()
seeds = st.integers(0, 2**32 - 1)


def _f32(x) -> np.ndarray:
    return np.asarray(x, np.float32)


def _pack(a: np.ndarray) -> np.ndarray:
    return _f32([a[i, k] for i, k in UPPER])


def _symmetric(rng: np.random.Generator, singular: np.ndarray) -> np.ndarray:
    """A float32-representable symmetric matrix with the given eigenvalues (before rounding)."""
    q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    a = _f32((q * singular) @ q.T).astype(np.float64)
    return (a + a.T) / 2  # exact: the rounded halves are symmetric already


def _solve(a: np.ndarray, b: np.ndarray, sweeps: int = 12) -> np.ndarray:
    return svd_solve(F(MIRROR, _pack(a)), F(MIRROR, _f32(b)), sweeps).v.astype(np.float64)


@settings(max_examples=30, deadline=None)
@given(seed=seeds, scale=st.floats(-3, 9), sweeps=st.sampled_from([12, 30]))
def test_svd_solve_matches_numpy_on_well_conditioned_systems(seed, scale, sweeps):
    rng = np.random.default_rng(seed)
    a = _symmetric(rng, 10 ** (scale + rng.uniform(0, 3, 6)))
    b = _f32(rng.normal(size=6) * 10**scale).astype(np.float64)
    x = _solve(a, b, sweeps)
    expect = np.linalg.solve(a, b)
    assert np.linalg.norm(x - expect) <= 1e-3 * np.linalg.norm(expect)


@settings(max_examples=25, deadline=None)
@given(seed=seeds, rank=st.integers(1, 5))
def test_svd_solve_is_the_pseudo_inverse_when_rank_deficient(seed, rank):
    """Directions with zero singular value are dropped, not amplified into huge steps."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    s = np.zeros(6)
    s[:rank] = 10 ** rng.uniform(0, 3, rank)
    a = _f32((q * s) @ q.T).astype(np.float64)
    b = _f32(rng.normal(size=6)).astype(np.float64)
    x = _solve(a, b, 30)
    expect = (q[:, :rank] / s[:rank]) @ (q[:, :rank].T @ b)
    assert np.all(np.isfinite(x))
    assert np.linalg.norm(x - expect) <= 2e-2 * np.linalg.norm(expect)


def test_svd_solve_of_degenerate_systems_is_finite():
    zero = np.zeros((6, 6))
    assert np.array_equal(_solve(zero, np.ones(6)), np.zeros(6))
    diag = np.diag([4.0, 0.0, 2.0, 0.0, 1.0, 8.0])  # already diagonal: every sweep idles
    x = _solve(diag, np.arange(1.0, 7.0))
    assert np.allclose(x, [0.25, 0.0, 1.5, 0.0, 5.0, 0.75], rtol=1e-6, atol=0)


@settings(max_examples=25, deadline=None)
@given(seed=seeds, rows=st.integers(6, 16))
@example(seed=25895223, rows=6)  # cond(J) = 5e5: a tight forward bound fails
def test_pinv_step_is_the_least_squares_step(seed, rows):
    rng = np.random.default_rng(seed)
    jac = _f32(rng.normal(size=(rows, 6)) * 10 ** rng.uniform(-1, 2, 6)).astype(np.float64)
    res = _f32(rng.normal(size=rows)).astype(np.float64)
    step = pinv_step(F(MIRROR, _f32(jac)), F(MIRROR, _f32(res))).v.astype(np.float64)
    expect = -np.linalg.lstsq(jac, res, rcond=None)[0]
    # float32 can promise no better than cond(J) * eps forward (CI drew a square J with
    # cond 5e5: 2e-3 off, 0.06 of that bound); the normal equations hold to ~eps backward
    # (over 600 seeds: forward <= 4 cond eps, backward <= 2.8e-7)
    eps = 2.0**-24
    assert np.linalg.norm(step - expect) <= 16 * np.linalg.cond(jac) * eps * np.linalg.norm(expect)
    norm_j = np.linalg.norm(jac, 2)
    backward = np.linalg.norm(jac.T @ (jac @ step + res)) / (
        norm_j * (norm_j * np.linalg.norm(step) + np.linalg.norm(res)))
    assert backward <= 2.0**-19


def _scene(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    axis = rng.normal(size=3)
    k = np.cross(np.eye(3), axis / np.linalg.norm(axis))
    angle = rng.uniform(0, np.pi)
    R = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    t = np.array([*rng.normal(0, 0.3, 2), rng.uniform(3, 6)])
    world = rng.normal(0, 1, (n, 3))
    cam = world @ R.T + t
    image = cam[:, :2] / cam[:, 2:] + rng.normal(0, 1e-3, (n, 2))
    weights = rng.uniform(3e5, 6e5, (n, 2))
    return {k: _f32(v) for k, v in
            {"R": R, "t": t, "image": image, "world": world, "weights": weights}.items()}


@settings(max_examples=20, deadline=None)
@given(seed=seeds, n=st.integers(4, 9))
@example(seed=16275, n=4)  # g cancels here: a componentwise bound failed
def test_weighted_system_matches_the_normal_equations(seed, n):
    """J_w^T J_w and J_w^T r_w are H and g; the cost is the LDL^T program's, bit for bit."""
    v = _scene(np.random.default_rng(seed), n)
    args = [F(MIRROR, v[k]) for k in ("R", "t", "image", "world", "weights")]
    jac, res, cost = (x.v.astype(np.float64) for x in weighted_system(*args))
    assert jac.shape == (2 * n, 6) and res.shape == (2 * n,)
    hess, grad, cost64 = normal_equations64(*(v[k].astype(np.float64) for k in
                                              ("R", "t", "image", "world", "weights")))
    # J is in the 13-bit normal-equation format (loc/normal.py); normwise, over 1800
    # random scenes: H off by <= 2^-19.3 |H|, g (which cancels near the optimum) by
    # <= 2^-10.7 |J| |r|
    assert np.linalg.norm(jac.T @ jac - hess) <= 2.0**-16 * np.linalg.norm(hess)
    assert np.linalg.norm(jac.T @ res - grad) <= 2.0**-9 * np.linalg.norm(jac, 2) * \
        np.linalg.norm(res)
    assert abs(cost - cost64) <= 1e-4 * cost64
    assert np.float32(cost) == normal_equations(*args)[2].v


@pytest.fixture(scope="module")
def svd_circuit():
    b = CircuitBuilder()
    be = CircuitBackend(b)
    packed = F(be, b.input("packed", (21,), bits=32, dtype="float32"))
    rhs = F(be, b.input("rhs", (6,), bits=32, dtype="float32"))
    with be.shallow():
        b.output("x", svd_solve(packed, rhs, sweeps=1).v, dtype="float32")
    return b.build()


def test_svd_circuit_equals_mirror_bit_for_bit(svd_circuit):
    """One sweep keeps the circuit small; every gate of bidiagonalization, sweep (with its
    split selects) and back-transformation is in it. Cases: well conditioned, rank
    deficient, diagonal (all splits) and zero."""
    rng = np.random.default_rng(5)
    mats = [_symmetric(rng, 10 ** rng.uniform(0, 3, 6)),
            _symmetric(rng, np.array([1e3, 20.0, 5.0, 1.0, 0.0, 0.0])),
            np.diag([3.0, 0.5, 7.0, 2.0, 0.0, 1.0]), np.zeros((6, 6))]
    packed = np.stack([_pack(a) for a in mats])
    rhs = _f32(rng.normal(size=(len(mats), 6)))
    out = evaluate(svd_circuit, {"packed": packed, "rhs": rhs}, batch=len(mats))
    for i in range(len(mats)):
        mirror = svd_solve(F(MIRROR, packed[i]), F(MIRROR, rhs[i]), sweeps=1).v
        assert np.array_equal(_f32(out["x"][i]).view(np.uint32), mirror.view(np.uint32)), i


def test_bad_shapes_and_sweeps_are_named():
    with pytest.raises(ValueError, match="m >= 6"):
        pinv_step(F(MIRROR, np.zeros((5, 6), np.float32)), F(MIRROR, np.zeros(5, np.float32)))
    with pytest.raises(ValueError, match="sweeps must be positive"):
        svd_solve(F(MIRROR, np.ones(21, np.float32)), F(MIRROR, np.ones(6, np.float32)), 0)
