"""Rotations and poses in the clear: the client applies each step it gets back from an
iteration here, so the circuits never need trigonometry."""

from __future__ import annotations

import numpy as np

from .types import Pose

# Below this angle the closed form loses digits to cancellation; the Taylor series is exact
# to double precision there (next terms are O(theta^6) ~ 1e-24).
_SMALL_ANGLE = 1e-4


def hat(w: np.ndarray) -> np.ndarray:
    """The cross-product matrix [w]x, so that hat(w) @ x == cross(w, x)."""
    wx, wy, wz = np.asarray(w, dtype=np.float64)
    return np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])


def so3_exp(w: np.ndarray) -> np.ndarray:
    """exp([w]x): the rotation by angle |w| about w (this is also Rodrigues' formula, so it
    turns an OpenCV rvec into its matrix)."""
    w = np.asarray(w, dtype=np.float64).reshape(3)
    theta2 = float(w @ w)
    if theta2 < _SMALL_ANGLE**2:
        a = 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0
        b = 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0
    else:
        theta = np.sqrt(theta2)
        a = np.sin(theta) / theta
        b = (1.0 - np.cos(theta)) / theta2
    k = hat(w)
    return np.eye(3) + a * k + b * (k @ k)


def rvec_from_matrix(R: np.ndarray) -> np.ndarray:
    """The Rodrigues vector of a rotation matrix (log map), full precision at every angle.

    Not cv2.Rodrigues: it returns 0 for every rotation below 1e-5 rad (0.008 px at f = 800).
    Below pi/2 the skew part sin(theta) * axis is well conditioned; above it the axis comes
    from the symmetric part (1 - cos(theta)) * axis axis^T, signed by the skew part.
    """
    R = np.asarray(R, dtype=np.float64)
    skew = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = float(np.linalg.norm(skew))
    c = float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    theta = np.arctan2(s, c)
    if c > 0:
        return skew * (theta / s) if s > 0 else np.zeros(3)
    sym = 0.5 * (R + R.T) - c * np.eye(3)
    k = int(np.argmax(np.diag(sym)))
    axis = sym[:, k] / np.sqrt(sym[k, k] * (1.0 - c))
    return theta * (axis if axis @ skew >= 0 else -axis)


def pose_from_rvec_tvec(rvec: np.ndarray, tvec: np.ndarray) -> Pose:
    """An OpenCV (rvec, tvec) as the matrix pose the circuits take."""
    return Pose(R=so3_exp(rvec), t=np.asarray(tvec, dtype=np.float64).reshape(3).copy())


def pose_to_rvec_tvec(pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """The matrix pose as OpenCV's (rvec, tvec)."""
    return rvec_from_matrix(pose.R), np.asarray(pose.t, dtype=np.float64).reshape(3).copy()


def apply_step(pose: Pose, step: np.ndarray) -> Pose:
    """types.py's update for step = (v, w): R' = exp([w]x) R, t' = exp([w]x) t + v."""
    step = np.asarray(step, dtype=np.float64).reshape(6)
    d_rot = so3_exp(step[3:])
    return Pose(R=d_rot @ pose.R, t=d_rot @ pose.t + step[:3])
