"""Clear-text localization: geometry, preprocessing, the float64 iteration, synthetic scenes,
and the reference LM/GN solvers against OpenCV."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from shared_paths import EXAMPLES

from snail_common.loc.accuracy import compare_with_opencv
from snail_common.loc.backends import Float64Backend
from snail_common.loc.geometry import (
    apply_step,
    pose_from_rvec_tvec,
    pose_to_rvec_tvec,
    rvec_from_matrix,
    so3_exp,
)
from snail_common.loc.pipeline import Options, localize
from snail_common.loc.preprocess import distortion_weights, normalize, pad
from snail_common.loc.problem import PoseVectors, Problem, ProblemError, load_problem
from snail_common.loc.reference import iteration_float64, reprojection_rms, residuals_and_jacobian
from snail_common.loc.synthetic import random_scene

EXAMPLE_FILES = sorted(EXAMPLES.glob("*.json"))
SCENES = 500  # random synthetic scenes for the OpenCV comparison
DISTORTED_SCENES = 200
FAST = settings(max_examples=40, deadline=None)

vec3 = arrays(np.float64, 3, elements=st.floats(-1.0, 1.0))
rotation = arrays(np.float64, 3, elements=st.floats(-1.7, 1.7))  # |r| < 3 < pi


def _scene(seed: int, n: int = 12) -> Problem:
    return random_scene(np.random.default_rng(seed), n)


def _with(problem: Problem, **fields) -> Problem:
    return Problem(**{**problem.__dict__, **fields})


def solve_float64(problem: Problem, algorithm: str = "lm", **options):
    """The plain reference solve: the pipeline on the float64 backend."""
    return localize(problem, Options(algorithm, min_invocations=0, **options),
                    Float64Backend())


# --- geometry ------------------------------------------------------------------------

@FAST
@given(rotation)
def test_exp_is_rodrigues_and_log_inverts_it(r):
    R = so3_exp(r)
    np.testing.assert_allclose(R, cv2.Rodrigues(r)[0], atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(rvec_from_matrix(R), r, atol=1e-9)


@FAST
@given(arrays(np.float64, 3, elements=st.floats(-1.0, 1.0)),
       st.floats(1e-12, 1e-3) | st.floats(np.pi - 1e-3, np.pi - 1e-12))
def test_log_is_exact_at_tiny_angles_and_near_pi(axis, angle):
    if np.linalg.norm(axis) < 1e-3:
        return
    w = axis / np.linalg.norm(axis) * angle
    np.testing.assert_allclose(rvec_from_matrix(so3_exp(w)), w, rtol=1e-6,
                               atol=1e-12 * angle)
    np.testing.assert_allclose(so3_exp(rvec_from_matrix(so3_exp(w))), so3_exp(w), atol=1e-12)


@FAST
@given(arrays(np.float64, 3, elements=st.floats(-1.0, 1.0)),
       st.floats(1e-12, 1e-3))
def test_exp_small_angles_keep_full_precision(axis, angle):
    if np.linalg.norm(axis) < 1e-3:
        return
    w = axis / np.linalg.norm(axis) * angle
    R = so3_exp(w)
    np.testing.assert_allclose(R @ w, w, rtol=0, atol=1e-18)  # the axis is fixed
    # First-order part is exactly [w]x; the rest is O(angle^2).
    skew = (R - R.T) / 2.0
    np.testing.assert_allclose([skew[2, 1], skew[0, 2], skew[1, 0]],
                               w * np.sinc(angle / np.pi), rtol=1e-12, atol=1e-16 * angle)


@FAST
@given(rotation, vec3, vec3, vec3)
def test_apply_step_follows_types_convention(r, t, v, w):
    pose = pose_from_rvec_tvec(r, t)
    step = np.concatenate([v, w * 0.3])
    new = apply_step(pose, step)
    X = np.array([0.3, -0.2, 1.5])
    expected = so3_exp(step[3:]) @ (pose.R @ X + pose.t) + step[:3]
    np.testing.assert_allclose(new.R @ X + new.t, expected, atol=1e-12)
    rvec, tvec = pose_to_rvec_tvec(pose)
    np.testing.assert_allclose(rvec, r, atol=1e-9)
    np.testing.assert_array_equal(tvec, t)


# --- preprocessing -------------------------------------------------------------------

@FAST
@given(st.integers(0, 10_000), rotation, vec3)
def test_frame_round_trip_and_same_camera_points(seed, r, t):
    problem = _scene(seed)
    nrm, frame = normalize(problem)
    np.testing.assert_allclose(nrm.world.mean(axis=0), 0.0, atol=1e-12)
    assert np.sqrt(np.mean(np.sum(nrm.world**2, axis=1))) == pytest.approx(1.0)
    pose = pose_from_rvec_tvec(r, t)
    there = frame.to_normalized(pose)
    back = frame.to_original(there)
    np.testing.assert_allclose(back.R, pose.R, atol=1e-15)
    np.testing.assert_allclose(back.t, pose.t, atol=1e-12)
    # The camera points differ only by the map scale, so projections are identical.
    cam = problem.points3d @ pose.R.T + pose.t
    cam_n = nrm.world @ there.R.T + there.t
    np.testing.assert_allclose(cam, frame.scale * cam_n, atol=1e-12)


@pytest.mark.parametrize("dist", [np.zeros(5), np.array([-0.2, 0.05, 1e-3, -1e-3, 0.0])])
def test_cost_is_in_squared_pixels(dist):
    problem = _with(_scene(3), dist=dist)
    nrm, frame = normalize(problem)
    rvec, tvec = problem.initial_pose.rvec, problem.initial_pose.tvec
    pose_n = frame.to_normalized(pose_from_rvec_tvec(rvec, tvec))
    cost = iteration_float64(nrm, pose_n, 1e-3).cost
    if not dist.any():  # exactly OpenCV's pixel cost
        assert frame.rms_px(cost) == pytest.approx(reprojection_rms(problem, rvec, tvec),
                                                   rel=1e-9)
    # Undistorted observations re-distort onto the pixels they came from.
    rays = np.column_stack([nrm.image, np.ones(problem.n)])
    pix, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), problem.K, dist)
    np.testing.assert_allclose(pix.reshape(-1, 2), problem.points2d, atol=1e-6)


def _distorted(problem: Problem, dist: np.ndarray, rng: np.random.Generator) -> Problem:
    """The same scene seen through a distorting lens, with fresh 0.5 px noise."""
    ref = problem.reference_pose
    clean, _ = cv2.projectPoints(problem.points3d, ref.rvec, ref.tvec, problem.K, dist)
    return _with(problem, dist=dist,
                 points2d=clean.reshape(-1, 2) + rng.normal(scale=0.5, size=(problem.n, 2)))


def test_distortion_weights():
    problem = _scene(4, n=30)
    nrm, _ = normalize(problem)
    np.testing.assert_array_equal(nrm.weights, np.ones(problem.n))
    k1 = -0.3  # radial only: scales 1 + 3 k1 r^2 (radial) and 1 + k1 r^2 (tangential)
    bent = _distorted(problem, np.array([k1, 0.0, 0.0, 0.0, 0.0]), np.random.default_rng(4))
    nrm, _ = normalize(bent)
    r2 = np.sum(nrm.image**2, axis=1)
    np.testing.assert_allclose(distortion_weights(bent, nrm.image),
                               (1 + k1 * r2) * (1 + 3 * k1 * r2), rtol=1e-7)
    np.testing.assert_array_equal(nrm.weights, distortion_weights(bent, nrm.image))
    # With the weights the cost stays close to OpenCV's (distorted) pixel cost.
    strong = _distorted(problem, np.array([-0.3, 0.1, 1e-3, -1e-3, 0.0]),
                        np.random.default_rng(4))
    nrm, frame = normalize(strong)
    for pose in (strong.initial_pose, strong.reference_pose):
        cost = iteration_float64(nrm, frame.to_normalized(pose_from_rvec_tvec(
            pose.rvec, pose.tvec)), 0.0).cost
        assert frame.rms_px(cost) == pytest.approx(
            reprojection_rms(strong, pose.rvec, pose.tvec), rel=0.05)


def test_coincident_map_points_are_rejected():
    problem = _scene(1)
    same = _with(problem, points3d=np.repeat(problem.points3d[:1], problem.n, axis=0))
    with pytest.raises(ProblemError, match=r"^points3d: all points coincide"):
        normalize(same)


def test_padding_changes_nothing():
    problem = _scene(5, n=7)
    nrm, frame = normalize(problem)
    padded = pad(nrm, 16)
    assert padded.n == 16 and np.all(padded.weights[7:] == 0) and np.all(padded.weights[:7] == 1)
    assert np.all(np.isfinite(padded.world)) and np.all(np.isfinite(padded.image))
    pose = frame.to_normalized(pose_from_rvec_tvec(problem.initial_pose.rvec,
                                                   problem.initial_pose.tvec))
    assert np.all((padded.world @ pose.R.T + pose.t)[:, 2] > 0)
    a, b = iteration_float64(nrm, pose, 1e-2), iteration_float64(padded, pose, 1e-2)
    assert b.cost == pytest.approx(a.cost, rel=1e-13)
    np.testing.assert_allclose(b.step, a.step, rtol=1e-10, atol=1e-14)
    with pytest.raises(ValueError, match=r"^n_total: 5 is fewer than the 7 points"):
        pad(nrm, 5)


# --- the float64 iteration -----------------------------------------------------------

@FAST
@given(st.integers(0, 10_000))
def test_jacobian_matches_finite_differences(seed):
    problem = _scene(seed, n=6)
    nrm, frame = normalize(problem)
    pose = frame.to_normalized(pose_from_rvec_tvec(problem.initial_pose.rvec,
                                                   problem.initial_pose.tvec))
    _, jac = residuals_and_jacobian(nrm, pose)
    h = 1e-6
    for k in range(6):
        e = np.zeros(6)
        e[k] = h
        plus, _ = residuals_and_jacobian(nrm, apply_step(pose, e))
        minus, _ = residuals_and_jacobian(nrm, apply_step(pose, -e))
        np.testing.assert_allclose(jac[:, :, k], (plus - minus) / (2 * h), rtol=1e-5, atol=1e-8)


@pytest.mark.parametrize("lam", [0.0, 1e-3, 10.0])
def test_step_solves_damped_normal_equations(lam):
    problem = _scene(11, n=9)
    nrm, frame = normalize(problem)
    nrm = type(nrm)(nrm.image, nrm.world, np.linspace(0.5, 2.0, nrm.n), nrm.axis_weights)
    pose = frame.to_normalized(pose_from_rvec_tvec(problem.initial_pose.rvec,
                                                   problem.initial_pose.tvec))
    res = iteration_float64(nrm, pose, lam)
    r, jac = residuals_and_jacobian(nrm, pose)
    W = np.repeat(nrm.weights, 2) * np.tile(nrm.axis_weights, nrm.n)
    J, rr = jac.reshape(-1, 6), r.reshape(-1)
    H = J.T @ (W[:, None] * J)
    np.testing.assert_allclose((H + lam * np.diag(np.diag(H))) @ res.step, -J.T @ (W * rr),
                               rtol=1e-8, atol=1e-8 * np.abs(H).max())
    assert res.cost == pytest.approx(float(W @ rr**2), rel=1e-12)


# --- synthetic scenes ----------------------------------------------------------------

@FAST
@given(st.integers(0, 10_000), st.integers(4, 40))
def test_synthetic_scenes_are_as_specified(seed, n):
    p = random_scene(np.random.default_rng(seed), n)
    again = random_scene(np.random.default_rng(seed), n)
    np.testing.assert_array_equal(p.points2d, again.points2d)
    assert p.n == n and p.image_size in ((640, 480), (1280, 960))
    assert 600 <= p.K[0, 0] <= 800
    ref = pose_from_rvec_tvec(p.reference_pose.rvec, p.reference_pose.tvec)
    ini = pose_from_rvec_tvec(p.initial_pose.rvec, p.initial_pose.tvec)
    assert np.all((p.points3d @ ref.R.T + ref.t)[:, 2] > 1.0)
    clean = noise_free(p)
    w, h = p.image_size
    assert np.all((clean >= 0) & (clean <= [w - 1, h - 1]))
    assert np.all(np.abs(p.points2d - clean) < 5.0)  # 10 sigma of 0.5 px noise
    angle = np.degrees(np.linalg.norm(rvec_from_matrix(ini.R @ ref.R.T)))
    assert 2.0 - 1e-9 <= angle <= 5.0 + 1e-9
    offset = np.linalg.norm(ini.t - ref.t) / np.linalg.norm(ref.t)
    assert offset == pytest.approx(0.05)


def noise_free(p: Problem) -> np.ndarray:
    pix, _ = cv2.projectPoints(p.points3d, p.reference_pose.rvec, p.reference_pose.tvec,
                               p.K, p.dist)
    return pix.reshape(-1, 2)


def test_reprojection_rms_measures_pixels():
    p = random_scene(np.random.default_rng(8), 256)
    exact = _with(p, points2d=noise_free(p))
    assert reprojection_rms(exact, p.reference_pose.rvec, p.reference_pose.tvec) < 1e-9
    # 0.5 px per axis: E|e|^2 = 2 * 0.25, RMS ~ 0.707 px.
    assert 0.6 < reprojection_rms(p, p.reference_pose.rvec, p.reference_pose.tvec) < 0.8


# --- reference solvers against OpenCV ------------------------------------------------

@pytest.mark.parametrize("algorithm", ["lm", "gn"])
@pytest.mark.parametrize("path", EXAMPLE_FILES, ids=lambda p: p.name)
def test_reference_matches_opencv_on_examples(path, algorithm):
    problem = load_problem(path)
    sol = solve_float64(problem, algorithm)
    cmp = compare_with_opencv(problem, sol.rvec, sol.tvec)
    assert cmp["ok"] and cmp["ok_refine_lm"], cmp
    assert sol.converged and sol.iterations < 20
    assert sol.rms_px == pytest.approx(cmp["rms_px"])
    # Far better than where it started.
    start = reprojection_rms(problem, problem.initial_pose.rvec, problem.initial_pose.tvec)
    assert sol.rms_px < 0.5 * start


@pytest.mark.parametrize("algorithm", ["lm", "gn"])
def test_reference_matches_opencv_on_random_scenes(algorithm):
    rng = np.random.default_rng(20240501)
    results = []
    for _ in range(SCENES):
        problem = random_scene(rng, int(rng.choice([4, 5, 6, 8, 12, 32, 64])))
        sol = solve_float64(problem, algorithm)
        cmp = compare_with_opencv(problem, sol.rvec, sol.tvec)
        results.append((cmp["ok"], cmp["ok_refine_lm"], sol.converged))
    ok, ok_lm, converged = np.mean(results, axis=0)
    assert ok >= 0.99 and ok_lm >= 0.99, (ok, ok_lm)
    assert converged >= 0.99


@pytest.mark.parametrize("algorithm", ["lm", "gn"])
def test_reference_matches_opencv_through_strong_distortion(algorithm):
    rng = np.random.default_rng(77)
    dist = np.array([-0.3, 0.1, 1e-3, -1e-3, 0.0])
    ok = []
    for _ in range(DISTORTED_SCENES):
        problem = _distorted(random_scene(rng, int(rng.choice([4, 6, 12, 64]))), dist, rng)
        sol = solve_float64(problem, algorithm)
        ok.append(compare_with_opencv(problem, sol.rvec, sol.tvec)["ok"])
    assert np.mean(ok) >= 0.99


def test_padded_solve_agrees_and_behind_camera_is_refused():
    problem = _scene(21, n=6)
    a, b = solve_float64(problem), solve_float64(problem, pad_points=12)
    np.testing.assert_allclose(b.rvec, a.rvec, atol=1e-9)
    assert b.invocations == a.invocations
    flipped = _with(problem, initial_pose=PoseVectors(problem.initial_pose.rvec,
                                                      -problem.initial_pose.tvec))
    with pytest.raises(ProblemError, match="behind the camera"):
        solve_float64(flipped)


def test_gn_and_lm_reach_the_same_pose():
    problem = load_problem(EXAMPLES / "synthetic_n64.json")
    lm, gn = solve_float64(problem, "lm"), solve_float64(problem, "gn")
    np.testing.assert_allclose(lm.rvec, gn.rvec, atol=1e-5)
    np.testing.assert_allclose(lm.tvec, gn.tvec, atol=1e-4)
