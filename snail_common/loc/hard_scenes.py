"""Synthetic scenes of the kinds real frames bring and random 3D scenes do not (issue 32):
one AprilTag seen by a wide-angle camera, several tags on one plane, a few far points.

Real frames (tags from a detector's test photos, phone photos with a COLMAP model) showed
the fixed-point circuits losing Gauss-Newton where float64 did not: four coplanar
corners, f about 330-340 px on 640x480, a 6.5 cm tag at 0.2-2 m (10-105 px a side). These
generators draw such scenes at random, reproducibly from a numpy Generator, with the
starting pose a client would have: IPPE on the noisy corners of the largest tag (the one
of its two solutions that fits every corner best, as snail_client.inputs.apriltag does),
then moved 5 degrees and 10 % of the distance, so the start is as far off as a stale pose
or a bad IPPE branch. The world frame is the first tag's (a tag map's frame).
"""

from __future__ import annotations

import cv2
import numpy as np

from .geometry import rvec_from_matrix, so3_exp
from .problem import PoseVectors, Problem

KINDS = ("one-tag", "plane-tags", "far-few")
TAG_M = 0.065  # the tag's side: a 6.5 cm AprilTag, as on the real frames
WIDE = (640, 480)  # the wide-angle camera's image and focal range (pixels)
WIDE_FOCAL = (330.0, 340.0)
PHONE = (1056, 792)  # the phone frames' image size (same focal range)
START_DEG, START_FRAC = 5.0, 0.10  # how far the start is moved from IPPE's pose
_MAX_TRIES = 1000


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _camera(rng: np.random.Generator, size: tuple[int, int]) -> np.ndarray:
    f = rng.uniform(*WIDE_FOCAL)
    return np.array([[f, 0.0, size[0] / 2.0], [0.0, f, size[1] / 2.0], [0.0, 0.0, 1.0]])


def _project(K: np.ndarray, R: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    cam = pts @ R.T + t
    return (cam[:, :2] / cam[:, 2:3]) * K[[0, 1], [0, 1]] + K[:2, 2]


def _inside(pix: np.ndarray, size: tuple[int, int], margin: float = 2.0) -> bool:
    return bool(np.all((pix > margin) & (pix < np.array(size) - margin)))


def tag_corners(side: float = TAG_M) -> np.ndarray:
    """A tag's corners in its own frame (z = 0), in ArUco's order."""
    h = side / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def _plane_pose(rng: np.random.Generator, K: np.ndarray, size: tuple[int, int],
                distance: float, obliquity_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a plane whose origin projects to a random pixel at ``distance`` from the
    camera, its normal ``obliquity_deg`` away from the line of sight, spun at random
    about that normal."""
    pix = rng.uniform([0.1 * size[0], 0.1 * size[1]], [0.9 * size[0], 0.9 * size[1]])
    ray = np.append((pix - K[:2, 2]) / K[[0, 1], [0, 1]], 1.0)
    ray /= np.linalg.norm(ray)
    facing = -ray  # the plane's normal (its z axis) towards the camera when head-on
    tilt_axis = np.cross(facing, _unit(rng))
    tilt = so3_exp(tilt_axis / np.linalg.norm(tilt_axis) * np.deg2rad(obliquity_deg))
    z = tilt @ facing
    x = np.cross(_unit(rng), z)
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])  # plane -> camera
    return R, ray * distance


def _ippe_start(K: np.ndarray, corners: np.ndarray, observed: np.ndarray,
                world: np.ndarray, all_observed: np.ndarray,
                rng: np.random.Generator) -> PoseVectors:
    """IPPE on one tag's noisy corners (``corners`` in the world frame), the solution that
    fits every observation best, then moved START_DEG and START_FRAC of the distance."""
    count, rvecs, tvecs, _ = cv2.solvePnPGeneric(corners, observed, K, np.zeros(5),
                                                 flags=cv2.SOLVEPNP_IPPE)
    if not count:
        raise RuntimeError("IPPE found no pose")
    fits = [np.sum((_project(K, so3_exp(r.reshape(3)), t.reshape(3), world)
                    - all_observed) ** 2) for r, t in zip(rvecs, tvecs)]
    best = int(np.argmin(fits))
    R = so3_exp(np.asarray(rvecs[best], float).reshape(3))
    t = np.asarray(tvecs[best], float).reshape(3)
    R0 = so3_exp(_unit(rng) * np.deg2rad(START_DEG)) @ R
    t0 = t + START_FRAC * np.linalg.norm(t) * _unit(rng)
    return PoseVectors(rvec_from_matrix(R0), t0)


def one_tag(rng: np.random.Generator) -> Problem:
    """Four corners of one 6.5 cm tag, 10-200 px a side (log-uniform) in a 640x480
    wide-angle image, 0-70 degrees of obliquity, corner noise 0.1-0.5 px."""
    return plane_tags(rng, tags=1)


def plane_tags(rng: np.random.Generator, tags: int | None = None) -> Problem:
    """``tags`` (default 2-6) 6.5 cm tags on one plane (a board or a wall), 10-200 px a
    side, 0-70 degrees of obliquity, corner noise 0.1-0.5 px; the start is IPPE on the
    largest tag in the image."""
    count = int(rng.integers(2, 7)) if tags is None else tags
    for _ in range(_MAX_TRIES):
        K = _camera(rng, WIDE)
        side_px = float(np.exp(rng.uniform(np.log(10.0), np.log(200.0))))
        distance = K[0, 0] * TAG_M / side_px
        # tag centres on a board up to 8 tag sides across, the first at the origin
        centres = np.vstack([np.zeros(2), rng.uniform(-4, 4, size=(count - 1, 2)) * TAG_M])
        if count > 1 and np.min(_gaps(centres)) < 1.5 * TAG_M:
            continue
        world = np.concatenate([tag_corners() + np.append(c, 0.0) for c in centres])
        R, t = _plane_pose(rng, K, WIDE, distance, rng.uniform(0.0, 70.0))
        t = t - R @ np.append(centres.mean(axis=0), 0.0)  # the board's middle at the pixel
        pix = _project(K, R, t, world)
        if not _inside(pix, WIDE):
            continue
        observed = pix + rng.normal(scale=rng.uniform(0.1, 0.5), size=pix.shape)
        quads = observed.reshape(count, 4, 2)
        largest = int(np.argmax([abs(cv2.contourArea(q.astype(np.float32))) for q in quads]))
        start = _ippe_start(K, world[4 * largest:4 * largest + 4], quads[largest], world,
                            observed, rng)
        return _problem(K, WIDE, observed, world, start, R, t)
    raise RuntimeError("no tag layout fit the image")


def _gaps(centres: np.ndarray) -> np.ndarray:
    d = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    return d[np.triu_indices(len(centres), 1)]


def far_few(rng: np.random.Generator) -> Problem:
    """6-12 points 10-50 m away with a depth spread of 2-10 % (little parallax), spread
    over a 640x480 or 1056x792 image of a wide-angle camera, noise 0.2-1 px (matched
    features, as from a COLMAP model); the start is the true pose moved 3-5 degrees and
    5-10 % of the distance, as the real frames' were."""
    size = (WIDE, PHONE)[int(rng.integers(2))]
    K = _camera(rng, size)
    n = int(rng.integers(6, 13))
    pix = rng.uniform([0.05 * size[0], 0.05 * size[1]], [0.95 * size[0], 0.95 * size[1]],
                      size=(n, 2))
    near = float(rng.uniform(10.0, 50.0))
    depth = near * (1.0 + rng.uniform(0.0, rng.uniform(0.02, 0.10), size=n))
    cam = np.column_stack([(pix - K[:2, 2]) / K[0, 0], np.ones(n)]) * depth[:, None]
    R = so3_exp(_unit(rng) * rng.uniform(0.0, np.pi))
    t = rng.normal(size=3)
    world = (cam - t) @ R  # R^T (x_cam - t), row-wise
    observed = pix + rng.normal(scale=rng.uniform(0.2, 1.0), size=pix.shape)
    R0 = so3_exp(_unit(rng) * np.deg2rad(rng.uniform(3.0, 5.0))) @ R
    t0 = t + rng.uniform(0.05, 0.10) * near * _unit(rng)
    return _problem(K, size, observed, world, PoseVectors(rvec_from_matrix(R0), t0), R, t)


def _problem(K: np.ndarray, size: tuple[int, int], observed: np.ndarray, world: np.ndarray,
             start: PoseVectors, R: np.ndarray, t: np.ndarray) -> Problem:
    return Problem(K=K, dist=np.zeros(5), points2d=observed, points3d=world,
                   initial_pose=start, reference_pose=PoseVectors(rvec_from_matrix(R), t),
                   image_size=size)


GENERATORS = {"one-tag": one_tag, "plane-tags": plane_tags, "far-few": far_few}


def hard_scene(kind: str, rng: np.random.Generator) -> Problem:
    """A scene of ``kind`` (one of KINDS)."""
    if kind not in GENERATORS:
        raise ValueError(f"kind: expected one of {', '.join(KINDS)}, got {kind!r}")
    return GENERATORS[kind](rng)
