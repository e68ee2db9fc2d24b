"""The float64 reference: one iteration exactly per types.py (the `float64` backend and the
yardstick for the float32 circuits), pixel RMS as OpenCV measures it, and the end-to-end
solve of a problem file with any backend."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .driver import DriverResult, run
from .geometry import pose_from_rvec_tvec, pose_to_rvec_tvec
from .preprocess import normalize, pad
from .problem import Problem, check_in_front
from .types import IterationBackend, IterationResult, Normalized, Pose


def residuals_and_jacobian(nrm: Normalized, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Normalized residuals r (n, 2) and their analytic Jacobian (n, 2, 6) w.r.t. the step
    (v, w) under the left perturbation R' = exp([w]x) R, t' = exp([w]x) t + v."""
    xc = nrm.world @ pose.R.T + pose.t
    c = 1.0 / xc[:, 2]
    a, b = xc[:, 0] * c, xc[:, 1] * c
    r = np.stack([a - nrm.image[:, 0], b - nrm.image[:, 1]], axis=1)
    zero = np.zeros_like(a)
    du = np.stack([c, zero, -a * c, -a * b, 1.0 + a * a, -b], axis=1)
    dv = np.stack([zero, c, -b * c, -(1.0 + b * b), a * b, a], axis=1)
    return r, np.stack([du, dv], axis=1)


def iteration_float64(nrm: Normalized, pose: Pose, lam: float) -> IterationResult:
    """One LM (lam > 0) or GN (lam = 0) iteration in float64: the step solving
    (J^T W J + lam diag(J^T W J)) step = -J^T W r, and the cost at the input pose."""
    r, jac = residuals_and_jacobian(nrm, pose)
    w = nrm.weights[:, None] * nrm.axis_weights[None, :]  # (n, 2) per point and axis
    wjac = jac * w[:, :, None]
    hess = np.einsum("nip,niq->pq", wjac, jac)
    grad = np.einsum("nip,ni->p", wjac, r)
    cost = float(np.sum(w * r * r))
    damped = hess + lam * np.diag(np.diag(hess))
    return IterationResult(step=np.linalg.solve(damped, -grad), cost=cost)


def reprojection_rms(problem: Problem, rvec: np.ndarray, tvec: np.ndarray) -> float:
    """RMS over points of the Euclidean pixel error, with distortion, as OpenCV projects."""
    proj, _ = cv2.projectPoints(problem.points3d, np.asarray(rvec, dtype=np.float64),
                                np.asarray(tvec, dtype=np.float64), problem.K, problem.dist)
    err = proj.reshape(-1, 2) - problem.points2d
    return float(np.sqrt(np.mean(np.sum(err * err, axis=1))))


@dataclass(frozen=True)
class Solution:
    """A solved problem in the file's world frame; `run` is the driver's record (its pose and
    cost are in the normalized frame)."""

    rvec: np.ndarray
    tvec: np.ndarray
    rms_px: float
    run: DriverResult


def solve(problem: Problem, backend: IterationBackend, algorithm: str = "lm",
          max_iterations: int = 20, n_total: int | None = None) -> Solution:
    """Preprocess, (pad to n_total for a fixed-size circuit,) run the driver in the
    normalized frame from the initial pose, and report in the original frame."""
    check_in_front(problem)
    nrm, frame = normalize(problem)
    if n_total is not None:
        nrm = pad(nrm, n_total)
    pose0 = frame.to_normalized(pose_from_rvec_tvec(problem.initial_pose.rvec,
                                                    problem.initial_pose.tvec))
    result = run(algorithm, nrm, pose0, backend, max_iterations)
    rvec, tvec = pose_to_rvec_tvec(frame.to_original(result.pose))
    return Solution(rvec, tvec, reprojection_rms(problem, rvec, tvec), result)


def solve_float64(problem: Problem, algorithm: str = "lm", max_iterations: int = 20) -> Solution:
    """The plain reference solver (`--backend float64`)."""
    return solve(problem, iteration_float64, algorithm, max_iterations)
