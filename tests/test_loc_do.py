"""The data-oblivious LM baseline: Cayley update, agreement with its float64 reference and
with the client's LM driver over the LDL^T SIL mirror, monotone cost, and a circuit whose
cleartext evaluation is bit-identical to the mirror."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from snail_common.circuit import CircuitBuilder
from snail_common.circuit.builder import CircuitTooLarge, and_gate_limit
from snail_common.circuit.cleartext import evaluate
from snail_common.loc.backends import sil_values
from snail_common.loc.driver import run_lm
from snail_common.loc.geometry import so3_exp
from snail_common.loc.types import IterationResult, Normalized, Pose
from snail_common.pnp.do import (
    OUTPUT_SHAPES,
    cayley64,
    cayley_update,
    do_program,
    do_reference,
    do_states,
)
from snail_common.pnp.fops import CircuitBackend, F, MirrorBackend
from snail_common.pnp.sil import input_shapes
from snail_common.pnp.spec import Spec, run_mirror

MIRROR = MirrorBackend()
FOCAL = 800.0
seeds = st.integers(0, 2**32 - 1)


def _f32(x) -> np.ndarray:
    return np.asarray(x, np.float32)


def _rotation(rng: np.random.Generator, angle: float) -> np.ndarray:
    axis = rng.normal(size=3)
    return so3_exp(axis / np.linalg.norm(axis) * angle)


def scene(rng: np.random.Generator, n: int) -> tuple[Normalized, Pose, Pose]:
    """Map points around the origin 4-6 units in front of the camera, 0.5 px noise at
    f = 800, and a start pose 2-5 degrees and 5% off the true one."""
    R = _rotation(rng, rng.uniform(0, np.pi))
    t = np.array([*rng.normal(0, 0.3, 2), rng.uniform(4, 6)])
    world = rng.normal(0, 1, (n, 3))
    cam = world @ R.T + t
    image = cam[:, :2] / cam[:, 2:] + rng.normal(0, 0.5 / FOCAL, (n, 2))
    start = Pose(_rotation(rng, np.radians(rng.uniform(2, 5))) @ R,
                 t + 0.05 * np.linalg.norm(t) * rng.choice([-1, 1], 3) / np.sqrt(3))
    nrm = Normalized(image, world, np.ones(n), np.array([FOCAL**2, FOCAL**2]))
    return nrm, start, Pose(R, t)


def do_values(nrm: Normalized, pose: Pose, lam: float) -> dict[str, np.ndarray]:
    return sil_values(Spec("lm", "sil", "ldlt", nrm.n), nrm, pose, lam)


def _mirror_inputs(values: dict[str, np.ndarray]) -> dict[str, F]:
    return {k: F(MIRROR, v) for k, v in values.items()}


def test_cayley_update_is_a_rotation_close_to_exp():
    rng = np.random.default_rng(1)
    R, t = _rotation(rng, 1.0), rng.normal(size=3)
    step = np.array([0.01, -0.02, 0.03, 0.02, -0.05, 0.01])
    R1, t1 = (x.v.astype(np.float64) for x in cayley_update(
        F(MIRROR, _f32(R)), F(MIRROR, _f32(t)), F(MIRROR, _f32(step))))
    rot = cayley64(step[3:])
    assert np.abs(rot @ rot.T - np.eye(3)).max() < 1e-15
    assert np.abs(rot - so3_exp(step[3:])).max() < np.linalg.norm(step[3:]) ** 3
    assert np.abs(R1 - rot @ R).max() < 1e-6
    assert np.abs(t1 - (rot @ t + step[:3])).max() < 1e-6


@settings(max_examples=4, deadline=None)
@given(seed=seeds, solver=st.sampled_from(["ldlt", "svd"]))
def test_do_mirror_follows_its_float64_reference(seed, solver):
    """The cost never increases and the run ends where float64 ends. The steps on the way
    differ slightly (the circuit's J^T W J and J^T W r are narrow floats, normal.py), so
    intermediate costs are not compared; the optimum they lead to is the same."""
    nrm, start, _ = scene(np.random.default_rng(seed), 6)
    values = do_values(nrm, start, 1e-3)
    states = do_states(_mirror_inputs(values), solver, iterations=8)
    ref = do_reference(values, solver, iterations=8)
    costs = [float(s.cost.v) for s in states]
    assert all(b <= a for a, b in pairwise(costs))
    assert costs[-1] < 0.1 * costs[0]
    assert abs(costs[-1] - ref[-1]["cost"]) <= 1e-3 * ref[-1]["cost"]
    final = states[-1]
    assert np.abs(final.R.v - ref[-1]["R"]).max() < 5e-5
    assert np.abs(final.t.v - ref[-1]["t"]).max() < 5e-5 * np.linalg.norm(ref[-1]["t"])


def _sil_mirror(nrm: Normalized, pose: Pose, lam: float) -> IterationResult:
    spec = Spec("lm", "sil", "ldlt", nrm.n)
    out = run_mirror(spec, sil_values(spec, nrm, pose, lam))
    return IterationResult(out["step"].astype(np.float64), float(out["cost"]))


def _pixels(pose: Pose, world: np.ndarray) -> np.ndarray:
    cam = world @ pose.R.T + pose.t
    return FOCAL * cam[:, :2] / cam[:, 2:]


@settings(max_examples=3, deadline=None)
@given(seed=seeds, solver=st.sampled_from(["ldlt", "svd"]))
@example(seed=902, solver="svd")  # weak direction: float32 fixed points 1.3e-4 apart in R
def test_do_reaches_the_pose_of_the_lm_driver(seed, solver):
    """20 oblivious iterations land where the client's LM loop over the LDL^T SIL mirror
    does (exp-map steps there, Cayley here: same optimum). Poses are compared where the
    data pins them, in the image: along a weakly constrained direction float32 leaves the
    two fixed points up to ~1e-4 apart in R while their reprojections differ by < 0.002 px
    (over 150 random scenes: at most 0.0064 px, 80x below the 0.5 px noise)."""
    nrm, start, _ = scene(np.random.default_rng(seed), 6)
    lm = run_lm(nrm, start, _sil_mirror)
    out = do_program(_mirror_inputs(do_values(nrm, start, 1e-3)), solver)
    do = Pose(out["R"].v.astype(np.float64), out["t"].v.astype(np.float64))
    assert np.abs(_pixels(do, nrm.world) - _pixels(lm.pose, nrm.world)).max() < 0.02
    assert abs(float(out["cost"].v) - lm.cost) <= 1e-3 * lm.cost


def _do_circuit(n: int, iterations: int) -> CircuitBuilder:
    b = CircuitBuilder()
    be = CircuitBackend(b)
    shapes = input_shapes("lm", n)
    inputs = {k: F(be, b.input(k, s, bits=32, dtype="float32")) for k, s in shapes.items()}
    outputs = do_program(inputs, "ldlt", iterations)
    for k in OUTPUT_SHAPES:
        b.output(k, outputs[k].v, dtype="float32")
    return b


def test_do_circuit_equals_mirror_bit_for_bit():
    n, iterations = 4, 2
    shapes = input_shapes("lm", n)
    circuit = _do_circuit(n, iterations).build()
    rng = np.random.default_rng(3)
    cases = []
    for lam in (1e-3, 1e7):  # mostly accepted / a rejection clamped at LAMBDA_MAX
        nrm, start, _ = scene(rng, n)
        cases.append(do_values(nrm, start, lam))
    batch = {k: np.stack([c[k] for c in cases]) for k in shapes}
    out = evaluate(circuit, batch, batch=len(cases))
    for i, case in enumerate(cases):
        mirror = do_program(_mirror_inputs(case), "ldlt", iterations)
        for k in OUTPUT_SHAPES:
            assert np.array_equal(_f32(out[k][i]).view(np.uint32),
                                  _f32(mirror[k].v).view(np.uint32)), (i, k)


def test_an_and_limit_refuses_a_do_circuit_after_its_first_iteration():
    one, three = _do_circuit(4, 1).n_and, _do_circuit(4, 3).n_and
    # the first iteration fits; the projection from it is the three-iteration circuit's
    # exact size, since every iteration is the same gates on other wires
    with and_gate_limit(one), pytest.raises(
            CircuitTooLarge, match=rf"3 LM iterations of [0-9,]+ AND gates: about {three:,} "):
        _do_circuit(4, 3)


def test_bad_arguments_are_named():
    nrm, start, _ = scene(np.random.default_rng(0), 4)
    inputs = _mirror_inputs(do_values(nrm, start, 1e-3))
    with pytest.raises(ValueError, match="solver must be one of"):
        do_program(inputs, "qr")
    with pytest.raises(ValueError, match=r"iterations must be in 1\.\.99"):
        do_program(inputs, "ldlt", 0)
    with pytest.raises(ValueError, match="solver must be one of"):
        do_reference({k: v.v for k, v in inputs.items()}, "qr")
