"""The cost's quadratic model at a pose, from the normal equations a client-solve circuit
returns: the damped step, and the reduction of the cost the model predicts for a step (the
yardstick of a step's real reduction, and the measure of what is left to gain)."""

from __future__ import annotations

import math

import numpy as np

from .types import NormalEquations


def damped_step(hess: np.ndarray, grad: np.ndarray, lam: float) -> np.ndarray:
    """The step solving (H + lam diag(H)) step = -g (least squares if H is singular; all
    NaN if the circuit's numbers are not finite, which the driver then rejects)."""
    system = hess + lam * np.diag(np.diag(hess))
    if not (np.isfinite(system).all() and np.isfinite(grad).all()):
        return np.full(6, np.nan)
    return np.linalg.lstsq(system, -grad, rcond=None)[0]


def predicted_reduction(normal: NormalEquations, step: np.ndarray) -> float:
    """cost - model(step) = -(2 g.step + step^T H step): the cost is r^T W r (types.py),
    not half of it, hence the 2."""
    return -float(2.0 * normal.grad @ step + step @ normal.hess @ step)


def gain(normal: NormalEquations) -> float:
    """The most the model predicts any step could gain: the undamped (Gauss-Newton) step's
    predicted reduction, g^T H^-1 g (undamped, so a large damping cannot make it look
    small). Infinite unless H is positive definite: a model that is not convex bounds
    nothing, and the circuit's narrow sums can tip a near-singular H over."""
    if not (np.isfinite(normal.hess).all() and np.isfinite(normal.grad).all()):
        return math.inf
    curvature, axes = np.linalg.eigh(normal.hess)
    if curvature.min() <= 0.0:
        return math.inf
    return float(((axes.T @ normal.grad) ** 2 / curvature).sum())
