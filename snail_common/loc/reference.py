"""The float64 reference: one iteration exactly per types.py (the yardstick for the float32
circuits and the driver's tests), and pixel RMS as OpenCV measures it."""

from __future__ import annotations

import cv2
import numpy as np

from .problem import Problem
from .types import IterationResult, Normalized, Pose


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
