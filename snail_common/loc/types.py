"""The data that crosses the boundary between the client's clear-text side and one secure
iteration: a normalized problem, a pose, and what one iteration returns.

Conventions (shared by the float64 reference, the circuits and the driver):
- camera coordinates X_c = R X + t; normalized image point (a, b) = (x_c / z_c, y_c / z_c);
- residual r_i = (a_i - u_i, b_i - v_i); cost = sum_i w_i (sx * r_ix^2 + sy * r_iy^2) where
  (sx, sy) = axis_weights = (fx^2, fy^2), so the cost is in squared pixels;
- a step is (v, w) (translation first, then rotation): R' = exp([w]x) R, t' = exp([w]x) t + v;
- LM solves (J^T W J + lam * diag(J^T W J)) step = -J^T W r; GN is lam = 0.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Normalized:
    """A problem as the circuit sees it: undistorted normalized image points, map points
    centered (and scaled) by the client, per-point weights and the two axis weights."""

    image: np.ndarray  # (n, 2) float64
    world: np.ndarray  # (n, 3) float64
    weights: np.ndarray  # (n,) float64, 0 for padding points
    axis_weights: np.ndarray  # (2,) float64: fx^2, fy^2

    @property
    def n(self) -> int:
        return len(self.image)


@dataclass(frozen=True)
class Pose:
    R: np.ndarray  # (3, 3) float64 rotation matrix
    t: np.ndarray  # (3,) float64


@dataclass(frozen=True)
class NormalEquations:
    """J^T W J and J^T W r at a pose: with the cost there, the cost's quadratic model
    cost + 2 g.step + step^T H step, which the client knows when it solves."""

    hess: np.ndarray  # (6, 6) float64
    grad: np.ndarray  # (6,) float64


@dataclass(frozen=True)
class IterationResult:
    """What one (secure or reference) iteration returns: the step from the input pose and
    the cost at the input pose, and the normal equations when the circuit returns them
    (the client solves) rather than only the step."""

    step: np.ndarray  # (6,) float64: v (3), w (3)
    cost: float
    normal: NormalEquations | None = None


# One iteration: (problem, pose, lambda) -> step and cost at that pose.
IterationBackend = Callable[[Normalized, Pose, float], IterationResult]
