"""A frame of the tracking schedule: exactly K runs from the prediction, each one GN or LM
step (snail_common/loc/steps.py), checked against the float64 algebra and OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from snail_common.loc.backends import CircuitBackend, Float64Backend, MirrorBackend
from snail_common.loc.driver import LAMBDA_START
from snail_common.loc.geometry import apply_step, pose_from_rvec_tvec, so3_exp
from snail_common.loc.pipeline import Options, iteration_backend, refine_fixed
from snail_common.loc.preprocess import normalize
from snail_common.loc.problem import PoseVectors
from snail_common.loc.quadratic import damped_step
from snail_common.loc.reference import iteration_float64, residuals_and_jacobian
from snail_common.loc.steps import run_fixed
from snail_common.loc.synthetic import random_scene
from snail_common.loc.trust import pose_error

CONVERGED = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-12)


def _scene(seed: int, n: int = 12, off_deg: float = 1.0):
    """A random scene whose initial pose is ``off_deg`` from the truth (a prediction)."""
    rng = np.random.default_rng(seed)
    return random_scene(rng, n, rotation_deg=(off_deg, off_deg), translation_frac=0.01)


def _normal64(nrm, pose):
    r, jac = residuals_and_jacobian(nrm, pose)
    w = nrm.weights[:, None] * nrm.axis_weights[None, :]
    wjac = jac * w[:, :, None]
    return np.einsum("nip,niq->pq", wjac, jac), np.einsum("nip,ni->p", wjac, r)


@pytest.mark.parametrize("algorithm", ["lm", "gn"])
def test_one_run_is_one_step_from_the_prediction(algorithm):
    problem = _scene(1)
    nrm, frame = normalize(problem)
    pose0 = frame.to_normalized(pose_from_rvec_tvec(problem.initial_pose.rvec,
                                                    problem.initial_pose.tvec))
    walls: list[float] = []
    spec = Options(algorithm=algorithm).spec(problem.n)
    backend = Float64Backend()
    stepped = run_fixed(algorithm, nrm, pose0, iteration_backend(spec, backend, walls), 1)
    hess, grad = _normal64(nrm, pose0)
    lam = LAMBDA_START if algorithm == "lm" else 0.0
    want = apply_step(pose0, damped_step(hess, grad, lam))
    assert np.allclose(stepped.pose.R, want.R, atol=1e-12)
    assert np.allclose(stepped.pose.t, want.t, atol=1e-12)
    assert stepped.invocations == backend.invocations == len(walls) == 1
    assert stepped.steps == 1 and stepped.evaluated is pose0
    if algorithm == "gn":  # the undamped step is the float64 reference's own
        step = iteration_float64(nrm, pose0, 0.0).step
        assert np.allclose(stepped.pose.t, apply_step(pose0, step).t, atol=1e-12)


@pytest.mark.parametrize("runs", [1, 2, 3, 5])
def test_k_runs_are_exactly_k_and_close_in_on_opencv(runs):
    """Each run is one backend call whatever the data; more runs land closer to OpenCV's
    converged pose (from 1 degree off: 0.02-0.34 degrees after one step on these scenes,
    about 1e-3 after two, 1e-7 after five: quadratic convergence)."""
    errors = []
    for seed in range(10):
        problem = _scene(seed)
        backend = Float64Backend()
        result = refine_fixed(problem, Options(), backend, problem.initial_pose, runs)
        assert result.invocations == backend.invocations == runs
        assert not result.converged
        _, rvec, tvec = cv2.solvePnP(problem.points3d, problem.points2d, problem.K,
                                     problem.dist, problem.initial_pose.rvec.copy(),
                                     problem.initial_pose.tvec.copy(),
                                     useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        rvec, tvec = cv2.solvePnPRefineLM(problem.points3d, problem.points2d, problem.K,
                                          problem.dist, rvec, tvec, CONVERGED)
        cv = PoseVectors(rvec.reshape(3), tvec.reshape(3))
        errors.append(pose_error(result.rvec, result.tvec, cv)["rotation_deg"])
    bound = {1: 0.5, 2: 0.05, 3: 2e-3, 5: 1e-5}[runs]  # degrees, over 10 scenes
    assert max(errors) < bound, errors


def test_the_circuit_solve_retries_a_rejected_step_within_the_runs():
    """When the circuit returns only the step (the map-owner circuits), a rejected
    candidate costs a retry run at the same pose with more damping: still K runs."""
    problem = _scene(3, off_deg=25.0)
    nrm, frame = normalize(problem)
    pose0 = frame.to_normalized(pose_from_rvec_tvec(problem.initial_pose.rvec,
                                                    problem.initial_pose.tvec))
    spec = Options(solve="circuit").spec(problem.n)
    backend = Float64Backend()
    walls: list[float] = []
    kinds = []
    for runs in (1, 4, 8):
        stepped = run_fixed("lm", nrm, pose0, iteration_backend(spec, backend, walls), runs)
        assert stepped.invocations == runs
        kinds = [c.kind for c in stepped.history]
    assert kinds[0] == "start" and set(kinds[1:]) <= {"candidate", "retry"}
    assert stepped.cost <= stepped.start_cost


def test_a_frame_on_the_circuit_equals_its_float32_mirror_bit_for_bit():
    """refine_fixed through the circuit (evaluated in the clear) and through the numpy
    mirror: the same pose, bit for bit, in exactly K invocations each."""
    problem = _scene(5, n=6)
    results = []
    for backend in (CircuitBackend(), MirrorBackend()):
        result = refine_fixed(problem, Options(), backend, problem.initial_pose, 2)
        assert backend.invocations == result.invocations == 2
        results.append(result)
    assert np.array_equal(results[0].rvec, results[1].rvec)
    assert np.array_equal(results[0].tvec, results[1].tvec)


def test_the_answer_is_never_evaluated_so_rms_is_computed_in_the_clear():
    problem = _scene(7)
    result = refine_fixed(problem, Options(), Float64Backend(), problem.initial_pose, 1)
    proj, _ = cv2.projectPoints(problem.points3d, result.rvec, result.tvec, problem.K,
                                problem.dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - problem.points2d) ** 2, 1))))
    assert result.rms_px == pytest.approx(rms, rel=1e-12)
    R = so3_exp(result.rvec)
    assert np.isfinite(R).all()


def test_do_mode_has_no_fixed_steps():
    problem = _scene(2)
    with pytest.raises(ValueError, match="--mode do"):
        refine_fixed(problem, Options(mode="do", solve="circuit"), Float64Backend(),
                     problem.initial_pose, 1)


@pytest.mark.parametrize("solve", ["client", "circuit"])
def test_a_tracked_frame_steps_by_gauss_newton_unless_told_lm(solve):
    """The default step is undamped (a circuit that solves takes lambda 0: the map-owner
    frames); LM's damping, even at its lightest start, stops short of it."""
    problem = _scene(4, n=6)
    nrm, frame = normalize(problem)
    pose0 = frame.to_normalized(pose_from_rvec_tvec(problem.initial_pose.rvec,
                                                    problem.initial_pose.tvec))
    want = frame.to_original(apply_step(pose0, iteration_float64(nrm, pose0, 0.0).step))
    results = {step: refine_fixed(problem, Options(step=step, solve=solve), Float64Backend(),
                                  problem.initial_pose, 1) for step in ("gn", "lm")}
    assert np.allclose(so3_exp(results["gn"].rvec), want.R, atol=1e-9)
    assert np.allclose(results["gn"].tvec, want.t, atol=1e-9)
    assert Options().step == "gn"
    assert not np.allclose(results["lm"].tvec, want.t, atol=1e-9)


def test_an_unknown_step_is_named():
    with pytest.raises(ValueError, match="--step"):
        Options(step="newton")
