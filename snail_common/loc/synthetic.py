"""Random synthetic scenes like shared/examples, for the accuracy tests and benchmarks: a
camera, n points in front of it, 0.5 px pixel noise, and an initial pose 2-5 degrees and
5 % of |t| away from the true one. Seeded numpy Generators make every scene reproducible."""

from __future__ import annotations

import numpy as np

from .geometry import rvec_from_matrix, so3_exp
from .problem import PoseVectors, Problem

# (width, height, focal range) of the two example cameras.
CAMERAS = ((640, 480, (600.0, 650.0)), (1280, 960, (750.0, 800.0)))
MARGIN = 0.05  # keep projections this fraction of the image away from the border


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def random_scene(rng: np.random.Generator, n: int, *, noise_px: float = 0.5,
                 rotation_deg: tuple[float, float] = (2.0, 5.0),
                 translation_frac: float = 0.05, planar: bool = False) -> Problem:
    """A Problem with reference_pose = the pose the points were generated from.

    Points fill a random box in the camera's view: pixel positions uniform inside the image
    margins, depths uniform in [d, d + depth_range] with d in [2, 5] and depth_range in
    [0.5, 2]; ``planar`` puts them instead on one plane at depth d on the optical axis,
    tilted 0-45 degrees (a tag or a wall: the case where PnP is least well conditioned).
    The world frame is the camera frame moved by a random pose (rotation up to 0.5 rad),
    so the true rvec/tvec are as general as the examples'.
    """
    if n < 4:
        raise ValueError(f"n: need at least 4 points, got {n}")
    width, height, focal = CAMERAS[rng.integers(len(CAMERAS))]
    f = rng.uniform(*focal)
    K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    pix = rng.uniform([MARGIN * width, MARGIN * height],
                      [(1 - MARGIN) * width, (1 - MARGIN) * height], size=(n, 2))
    near = rng.uniform(2.0, 5.0)
    rays = np.column_stack([(pix - K[:2, 2]) / f, np.ones(n)])
    if planar:  # ray-plane intersection: normal . x = normal . (0, 0, near)
        normal = so3_exp(_unit(rng) * np.deg2rad(rng.uniform(0.0, 45.0)))[:, 2]
        depth = near * normal[2] / (rays @ normal)
    else:
        depth = rng.uniform(near, near + rng.uniform(0.5, 2.0), size=n)
    cam = rays * depth[:, None]
    rvec = _unit(rng) * rng.uniform(0.0, 0.5)
    R = so3_exp(rvec)
    tvec = np.array([0.0, 0.0, near + 0.5]) + rng.normal(scale=0.2, size=3)
    world = (cam - tvec) @ R  # R^T (x_cam - t), row-wise
    observed = pix + rng.normal(scale=noise_px, size=(n, 2))
    d_rot = so3_exp(_unit(rng) * np.deg2rad(rng.uniform(*rotation_deg)))
    rvec0 = rvec_from_matrix(d_rot @ R)
    tvec0 = tvec + translation_frac * np.linalg.norm(tvec) * _unit(rng)
    return Problem(K=K, dist=np.zeros(5), points2d=observed, points3d=world,
                   initial_pose=PoseVectors(rvec0, tvec0),
                   reference_pose=PoseVectors(rvec, tvec), image_size=(width, height))

