"""Random scenes of printed AprilTags for tests and accuracy sweeps: a board of 1-4 tags
(world frame = board frame, tags facing +z), a camera with random intrinsics and lens
distortion, and a viewpoint at a chosen obliquity (angle between the board's normal and
the line of sight to its centre). Seeded generators make every scene reproducible."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from snail_client.inputs.camera import Camera, intrinsics
from snail_client.inputs.tagmap import Tag, TagMap
from snail_common.loc.geometry import rvec_from_matrix, so3_exp
from snail_common.loc.problem import PoseVectors

from .render import Look

SIZE = (640, 480)
MARGIN_PX = 12  # every tag corner at least this far inside the image


@dataclass(frozen=True)
class TagScene:
    tagmap: TagMap
    camera: Camera
    pose: PoseVectors  # true world -> camera
    obliquity_deg: float
    distance: float  # camera centre to the board centre, metres
    look: Look


def random_camera(rng: np.random.Generator, distortion: bool = True) -> Camera:
    """A 640x480 camera, focal 500-700 px, principal point near the centre, and (when
    asked) radial and tangential distortion like a webcam's (k1 in [-0.3, 0.1])."""
    f = rng.uniform(500, 700)
    K = intrinsics(f * rng.uniform(0.99, 1.01), f, 319.5 + rng.uniform(-15, 15),
                   239.5 + rng.uniform(-15, 15))
    dist = np.zeros(5)
    if distortion:
        dist = np.array([rng.uniform(-0.3, 0.1), rng.uniform(-0.05, 0.1),
                         rng.uniform(-2e-3, 2e-3), rng.uniform(-2e-3, 2e-3), 0.0])
    return Camera(K, dist, SIZE)


def random_board(rng: np.random.Generator, tags: int | None = None) -> TagMap:
    """1-4 tags (or ``tags``) of one size (8-16 cm) on a grid in the z = 0 plane."""
    count = int(rng.integers(1, 5)) if tags is None else tags
    size = rng.uniform(0.08, 0.16)
    ids = rng.choice(587, size=count, replace=False)
    cols = int(np.ceil(np.sqrt(count)))
    spacing = 1.6 * size
    centres = [np.array([(i % cols) * spacing, -(i // cols) * spacing, 0.0])
               for i in range(count)]
    middle = np.mean(centres, axis=0)
    return TagMap("tag36h11", {int(i): Tag(int(i), size, np.zeros(3), c - middle)
                               for i, c in zip(ids, centres)})


def view(obliquity_deg: float, azimuth_deg: float, distance: float, roll_deg: float,
         target: np.ndarray | None = None) -> PoseVectors:
    """The world-to-camera pose of a camera ``distance`` from ``target``, seeing the board
    at ``obliquity_deg`` from its normal, rolled by ``roll_deg`` about its optical axis."""
    target = np.zeros(3) if target is None else target
    th, ph = np.radians(obliquity_deg), np.radians(azimuth_deg)
    centre = target + distance * np.array([np.sin(th) * np.cos(ph),
                                           np.sin(th) * np.sin(ph), np.cos(th)])
    z = (target - centre) / distance
    hint = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(hint, z)
    x /= np.linalg.norm(x)
    R = np.vstack([x, np.cross(z, x), z])
    R = so3_exp(np.array([0.0, 0.0, np.radians(roll_deg)])) @ R
    return PoseVectors(rvec_from_matrix(R), -R @ centre)


def _inside(tagmap: TagMap, camera: Camera, pose: PoseVectors) -> bool:
    corners = np.concatenate([t.corners_world() for t in tagmap.tags.values()])
    pix, _ = cv2.projectPoints(corners, pose.rvec, pose.tvec, camera.K, camera.dist)
    pix = pix.reshape(-1, 2)
    width, height = SIZE
    return bool(np.all((pix >= MARGIN_PX) & (pix <= [width - 1 - MARGIN_PX,
                                                     height - 1 - MARGIN_PX])))


def random_tag_scene(rng: np.random.Generator, obliquity: tuple[float, float] = (20, 70),
                     tags: int | None = None, distortion: bool = True,
                     look: Look | None = None) -> TagScene:
    """A board, a camera and a viewpoint whose tags all fall inside the image: distance
    3-7 tag sizes (closer when the board is larger), the line of sight aimed near the
    board's centre, roll up to 30 degrees; blur 0.5-1.2 px and noise 1-4 grey levels."""
    tagmap = random_board(rng, tags)
    camera = random_camera(rng, distortion)
    size = next(iter(tagmap.tags.values())).size
    spread = np.ptp([t.tvec for t in tagmap.tags.values()], axis=0).max() + size
    look = look or Look(blur_px=rng.uniform(0.5, 1.2), noise=rng.uniform(1, 4),
                        background=int(rng.integers(60, 160)))
    while True:
        obliquity_deg = rng.uniform(*obliquity)
        distance = rng.uniform(3, 7) * size * max(1.0, spread / (2 * size))
        pose = view(obliquity_deg, rng.uniform(0, 360), distance, rng.uniform(-30, 30),
                    np.append(rng.uniform(-0.15, 0.15, 2) * spread, 0.0))
        if _inside(tagmap, camera, pose):
            return TagScene(tagmap, camera, pose, obliquity_deg, distance, look)
