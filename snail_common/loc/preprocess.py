"""Client-side preprocessing, once per image: what the circuit sees is intrinsics-free,
well scaled data (normalized image points, map points centered with unit RMS radius), and
the pose moves between the file's world frame and that normalized frame.

Why the cost survives: with X = s Xn + c, the camera point of X under (R, t) is s times the
camera point of Xn under (R, (R c + t) / s), and a projection does not see a common scale.
So the image, the residuals and the cost (in squared pixels through the axis weights
fx^2, fy^2) are the same in both frames.

With lens distortion a normalized residual r becomes the pixel error f J r, J the 2x2
Jacobian of the distortion at that point. The per-point weight |det J| (1 without
distortion) keeps the cost in squared pixels to first order, as far as one scalar per point
can (J is not a similarity: radial and tangential scales differ). Unweighted, strong
distortion (k1 = -0.3) missed OpenCV's RMS by more than 0.5 % on 1 % of random scenes.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .problem import Problem, ProblemError
from .types import Normalized, Pose

# Undistortion is a fixed-point iteration (OpenCV defaults to 5 rounds, ~0.02 px off at
# k1 = -0.2); iterate until re-distorting lands within 1e-10 px of the observation.
_UNDISTORT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
_H = 1e-6  # difference step in normalized coordinates for the distortion Jacobian


@dataclass(frozen=True)
class Frame:
    """The similarity X = scale * Xn + center between world and normalized map frames."""

    center: np.ndarray  # (3,)
    scale: float
    n_points: int  # real (unpadded) points, for per-point figures

    def to_normalized(self, pose: Pose) -> Pose:
        return Pose(R=pose.R, t=(pose.R @ self.center + pose.t) / self.scale)

    def to_original(self, pose: Pose) -> Pose:
        return Pose(R=pose.R, t=self.scale * pose.t - pose.R @ self.center)

    def rms_px(self, cost: float) -> float:
        """RMS pixel error per point from a cost: the normalized-frame cost is already in
        squared pixels (scale 1; to first order under distortion), summed over real points."""
        return float(np.sqrt(max(cost, 0.0) / self.n_points))


def undistort(problem: Problem) -> np.ndarray:
    """Pixel observations as normalized, undistorted image coordinates (x/z, y/z)."""
    pts = problem.points2d.reshape(-1, 1, 2)
    out = cv2.undistortPoints(pts, problem.K, problem.dist, None, None, None, _UNDISTORT)
    return out.reshape(-1, 2).astype(np.float64)


def distortion_weights(problem: Problem, image: np.ndarray) -> np.ndarray:
    """|det J| of the distortion map at each undistorted point (central differences through
    cv2.projectPoints, ~1e-9 relative); exactly 1 when the camera has no distortion."""
    if not problem.dist.any():
        return np.ones(len(image))
    offsets = np.array([[_H, 0.0], [-_H, 0.0], [0.0, _H], [0.0, -_H]])
    rays = (image[None, :, :] + offsets[:, None, :]).reshape(-1, 2)
    pix, _ = cv2.projectPoints(np.column_stack([rays, np.ones(len(rays))]), np.zeros(3),
                               np.zeros(3), np.eye(3), problem.dist)
    pix = pix.reshape(4, -1, 2)
    dx, dy = (pix[0] - pix[1]) / (2 * _H), (pix[2] - pix[3]) / (2 * _H)
    return np.abs(dx[:, 0] * dy[:, 1] - dx[:, 1] * dy[:, 0])


def normalize(problem: Problem) -> tuple[Normalized, Frame]:
    """The circuit's view of a problem (weights 1, or |det J| of the distortion) and the
    frame to map poses back."""
    center = problem.points3d.mean(axis=0)
    centered = problem.points3d - center
    scale = float(np.sqrt(np.mean(np.sum(centered**2, axis=1))))
    if not scale > 1e-12 * max(1.0, float(np.abs(center).max())):  # rounding noise only
        raise ProblemError("points3d: all points coincide")
    fx, fy = problem.K[0, 0], problem.K[1, 1]
    image = undistort(problem)
    nrm = Normalized(image=image, world=centered / scale,
                     weights=distortion_weights(problem, image),
                     axis_weights=np.array([fx * fx, fy * fy]))
    return nrm, Frame(center=center, scale=scale, n_points=problem.n)


def pad(nrm: Normalized, n_total: int) -> Normalized:
    """Grow to the circuit's fixed size with weight-0 dummies. Each dummy copies the weighted
    real point nearest the map center, so it is finite and in front of the camera whenever
    the real points are, and contributes exactly nothing to the cost or the step."""
    if n_total < nrm.n:
        raise ValueError(f"n_total: {n_total} is fewer than the {nrm.n} points")
    live = np.flatnonzero(nrm.weights > 0)
    if not len(live):
        raise ValueError("weights: no point has a positive weight")
    src = live[np.argmin(np.sum(nrm.world[live] ** 2, axis=1))]
    extra = n_total - nrm.n
    return Normalized(image=np.vstack([nrm.image, np.repeat(nrm.image[src:src + 1], extra, 0)]),
                      world=np.vstack([nrm.world, np.repeat(nrm.world[src:src + 1], extra, 0)]),
                      weights=np.concatenate([nrm.weights, np.zeros(extra)]),
                      axis_weights=nrm.axis_weights)
