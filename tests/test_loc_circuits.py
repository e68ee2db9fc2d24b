"""SIL circuits: cleartext evaluation is bit-identical to the float32 mirror, and the mirror
solves the same normal equations as a float64 computation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from snail_common.circuit.cleartext import evaluate
from snail_common.circuit.schedule import schedule_circuit
from snail_common.loc.backends import CircuitBackend, sil_values
from snail_common.loc.types import Normalized, Pose
from snail_common.pnp.do import normal_equations64
from snail_common.pnp.normal import NORMAL_FRAC
from snail_common.pnp.spec import Spec, build, run_mirror

N = 5  # odd, so the tree sum over points carries a leftover


@pytest.fixture(scope="module", params=["lm", "gn"])
def compiled(request):
    spec = Spec(request.param, "sil", "ldlt", N)
    circuit = build(spec)
    return spec, circuit, schedule_circuit(circuit)


def _rotation(rng: np.random.Generator, max_angle: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(0, max_angle)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def random_values(spec: Spec, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A plausible iteration: centered map points 2-6 units in front of the camera, image
    points near their projections, pixel-scale weights (some points padded with 0)."""
    n = spec.points
    R = _rotation(rng, np.pi)
    t = np.array([*rng.normal(0, 0.3, 2), rng.uniform(2, 6)])
    world = rng.normal(0, 1, (n, 3))
    cam = world @ R.T + t
    image = cam[:, :2] / cam[:, 2:] + rng.normal(0, 0.01, (n, 2))
    weights = np.outer(rng.integers(0, 2, n) | (np.arange(n) < 4), rng.uniform(3e5, 6e5, 2))
    values = {"R": R, "t": t, "image": image, "world": world, "weights": weights}
    if spec.algorithm == "lm":
        values["lam"] = 10.0 ** rng.uniform(-6, 2)
    return {k: np.asarray(v, np.float32) for k, v in values.items()}


def _bits(x) -> np.ndarray:
    return np.asarray(x, np.float32).view(np.uint32)


def test_cleartext_equals_mirror_on_a_batch(compiled):
    spec, circuit, schedule = compiled
    rng = np.random.default_rng(7)
    cases = [random_values(spec, rng) for _ in range(64)]
    batch = {k: np.stack([c[k] for c in cases]) for k in cases[0]}
    out = evaluate(circuit, batch, schedule=schedule, batch=len(cases))
    for i, case in enumerate(cases):
        mirror = run_mirror(spec, case)
        assert np.array_equal(_bits(out["step"][i]), _bits(mirror["step"])), i
        assert _bits(out["cost"][i]) == _bits(mirror["cost"]), i


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_cleartext_equals_mirror_random(compiled, seed):
    spec, circuit, schedule = compiled
    values = random_values(spec, np.random.default_rng(seed))
    out = evaluate(circuit, values, schedule=schedule)
    mirror = run_mirror(spec, values)
    assert np.array_equal(_bits(out["step"]), _bits(mirror["step"]))
    assert _bits(out["cost"]) == _bits(mirror["cost"])


@pytest.mark.parametrize("algorithm", ["lm", "gn"])
def test_mirror_solves_the_normal_equations(algorithm):
    """The cost is float32-accurate; the step solves the float64 system up to the narrow
    J^T W J: its backward error |H x + g| / (|H| |x|) stays within two units of the
    NORMAL_FRAC format (a float32 H would give ~1e-7, a wrong entry ~1)."""
    spec = Spec(algorithm, "sil", "ldlt", 12)
    rng = np.random.default_rng(3)
    for _ in range(20):
        values = random_values(spec, rng)
        values["weights"][:] = np.float32(4e5)  # all points count: well conditioned
        v = {k: np.asarray(x, np.float64) for k, x in values.items()}
        hess, grad, cost = normal_equations64(v["R"], v["t"], v["image"], v["world"],
                                              v["weights"])
        if algorithm == "lm":
            hess = hess + v["lam"] * np.diag(np.diag(hess))
        mirror = run_mirror(spec, values)
        step = mirror["step"].astype(np.float64)
        assert abs(mirror["cost"] - cost) <= 1e-4 * cost
        backward = np.linalg.norm(hess @ step + grad) / (
            np.linalg.norm(hess, 2) * np.linalg.norm(step) + np.linalg.norm(grad))
        assert backward <= 2.0 ** (1 - NORMAL_FRAC)


def test_circuit_iteration_decodes_step_and_cost(compiled):
    spec, _, _ = compiled
    rng = np.random.default_rng(11)
    values = random_values(spec, rng)
    problem = Normalized(values["image"].astype(float), values["world"].astype(float),
                         np.ones(N), np.array([1.0, 1.0]))
    pose = Pose(values["R"].astype(float), values["t"].astype(float))
    lam = float(values.get("lam", 0.0))
    result = CircuitBackend().run(spec, sil_values(spec, problem, pose, lam))
    mirror = run_mirror(spec, sil_values(spec, problem, pose, lam))
    assert np.array_equal(result["step"], mirror["step"])
    assert result["cost"] == mirror["cost"]


@pytest.mark.parametrize("text", ["lm-sil-ldlt-n3", "lm-sil-qr-n6", "xx-sil-ldlt-n6",
                                  "lm-sil-ldlt-n06", "lm-sil-ldlt-n99999", "lm-sil-ldlt-6",
                                  "lm-do-ldlt-n6-i0", "lm-do-ldlt-n6-i100", "lm-sil-ldlt-n6-i2",
                                  "gn-do-ldlt-n6"])
def test_bad_circuit_ids_are_rejected(text):
    with pytest.raises(ValueError, match=r"circuit id|points must be|iteration|must be lm"):
        Spec.parse(text)


@pytest.mark.parametrize("spec", [Spec("gn", "sil", "ldlt", 64), Spec(mode="do"),
                                  Spec(mode="do", solver="svd", points=4, iterations=2)])
def test_circuit_id_round_trip(spec):
    assert Spec.parse(spec.circuit_id) == spec
    assert spec.circuit_id.endswith("-i2") == (spec.iterations == 2)


def test_wrong_point_count_is_named():
    spec = Spec("lm", "sil", "ldlt", 6)
    problem = Normalized(np.zeros((5, 2)), np.zeros((5, 3)), np.ones(5), np.ones(2))
    with pytest.raises(ValueError, match="takes 6 points, the problem has 5"):
        sil_values(spec, problem, Pose(np.eye(3), np.zeros(3)), 0.0)
