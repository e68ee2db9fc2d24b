"""AprilTag 36h11 images to 2D-3D matches, and a first pose in the clear.

Detection is OpenCV's ArUco module with its AprilTag dictionary (sub-pixel corner
refinement); each detected tag the map knows gives four matches in ArUco's corner order.
The first pose is IPPE on one tag (the largest in the image: its corners are the most
precise), the one of IPPE's two solutions that fits every matched corner best. It is
computed here, on the client, and only ever enters a circuit as a secret input.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from snail_common.loc.geometry import rvec_from_matrix, so3_exp
from snail_common.loc.problem import PoseVectors, Problem

from .camera import Camera
from .fields import InputError
from .tagmap import TagMap

_SHOWN = 12  # detected ids listed in an error at most


@dataclass(frozen=True)
class Detections:
    """Tags found in one image: ids (k,) and corners (k, 4, 2) in pixels, ArUco order."""

    ids: np.ndarray
    corners: np.ndarray


@dataclass(frozen=True)
class Matched:
    """The detections the map knows, as matches: 4 corners per tag, tags in id order."""

    tag_ids: list[int]
    points2d: np.ndarray  # (4k, 2)
    points3d: np.ndarray  # (4k, 3)
    unmapped: list[int]  # detected ids the map does not have
    repeated: list[int]  # ids detected more than once (which one is which? not used)


@functools.cache
def _detector(family: str) -> cv2.aruco.ArucoDetector:
    if family != "tag36h11":
        raise InputError(f"family: no detector for {family!r}")
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    return cv2.aruco.ArucoDetector(dictionary, params)


def read_image(path: str | Path) -> np.ndarray:
    """A grayscale image file; InputError naming it when it cannot be read."""
    if not Path(path).is_file():
        raise InputError(f"{path}: no such image file")
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise InputError(f"{path}: not an image OpenCV can read")
    return image


def detect(image: np.ndarray, family: str = "tag36h11") -> Detections:
    """Every tag of ``family`` in a grayscale (or BGR) image."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    corners, ids, _ = _detector(family).detectMarkers(image)
    if ids is None:
        return Detections(np.zeros(0, np.int64), np.zeros((0, 4, 2)))
    return Detections(ids.reshape(-1).astype(np.int64),
                      np.array(corners, np.float64).reshape(-1, 4, 2))


def match(detections: Detections, tagmap: TagMap, max_tags: int | None = None) -> Matched:
    """The map's tags among the detections (the ``max_tags`` largest in the image when
    given: a fixed number of points is one circuit and hides how many tags are in view);
    InputError naming what was detected when none of them is in the map."""
    ids, counts = np.unique(detections.ids, return_counts=True)
    repeated = [int(i) for i in ids[counts > 1]]
    usable = [int(i) for i in ids[counts == 1] if int(i) in tagmap.tags]
    unmapped = [int(i) for i in ids if int(i) not in tagmap.tags]
    if not usable:
        raise InputError(_nothing_mapped(detections, unmapped, repeated, tagmap))
    rows = [int(np.flatnonzero(detections.ids == i)[0]) for i in usable]
    if max_tags is not None and len(rows) > max_tags:
        areas = [_area(detections.corners[r]) for r in rows]
        keep = sorted(np.argsort(areas)[::-1][:max_tags])
        usable, rows = [usable[k] for k in keep], [rows[k] for k in keep]
    p2 = detections.corners[rows].reshape(-1, 2)
    p3 = np.concatenate([tagmap.tags[i].corners_world() for i in usable])
    return Matched(usable, p2, p3, unmapped, repeated)


def _nothing_mapped(detections: Detections, unmapped: list[int], repeated: list[int],
                    tagmap: TagMap) -> str:
    if not len(detections.ids):
        return f"no {tagmap.family} tag detected in the image"
    seen = ", ".join(map(str, sorted(set(detections.ids.tolist()))[:_SHOWN]))
    more = " ..." if len(set(detections.ids.tolist())) > _SHOWN else ""
    why = (f"; ids {repeated} were detected more than once and are ambiguous"
           if repeated else "")
    return (f"no mapped tag in the image: detected {tagmap.family} ids {seen}{more}, none "
            f"of them in the tag map{why} (its ids: "
            f"{', '.join(map(str, sorted(tagmap.tags)[:_SHOWN]))}"
            f"{' ...' if len(tagmap.tags) > _SHOWN else ''})")


def initial_pose(matched: Matched, tagmap: TagMap, camera: Camera) -> PoseVectors:
    """IPPE on the largest matched tag, composed with that tag's pose in the map; of its
    two solutions, the one with the smaller reprojection error over all matched corners."""
    quads = matched.points2d.reshape(-1, 4, 2)
    best = int(np.argmax([_area(q) for q in quads]))
    tag = tagmap.tags[matched.tag_ids[best]]
    count, rvecs, tvecs, _ = cv2.solvePnPGeneric(
        tag.corners_tag(), quads[best], camera.K, camera.dist,
        flags=cv2.SOLVEPNP_IPPE_SQUARE)
    if not count:
        raise InputError(f"tag {tag.id}: IPPE found no pose for its corners")
    R_tag, t_tag = so3_exp(tag.rvec), tag.tvec
    candidates = []
    for rvec, tvec in zip(rvecs, tvecs):
        R_ct = so3_exp(np.asarray(rvec, np.float64).reshape(3))  # tag -> camera
        R = R_ct @ R_tag.T  # world -> camera
        t = np.asarray(tvec, np.float64).reshape(3) - R @ t_tag
        candidates.append(PoseVectors(rvec_from_matrix(R), t))
    errors = [_reprojection(matched, camera, pose) for pose in candidates]
    return candidates[int(np.argmin(errors))]


def _area(quad: np.ndarray) -> float:
    return abs(cv2.contourArea(quad.astype(np.float32)))


def _reprojection(matched: Matched, camera: Camera, pose: PoseVectors) -> float:
    projected, _ = cv2.projectPoints(matched.points3d, pose.rvec, pose.tvec, camera.K,
                                     camera.dist)
    return float(np.sum((projected.reshape(-1, 2) - matched.points2d) ** 2))


def problem_from_image(image: np.ndarray, tagmap: TagMap, camera: Camera,
                       max_tags: int | None = None) -> tuple[Problem, Matched]:
    """The snail-problem of one image: matched corners as observed (the problem carries the
    camera's distortion; the client undistorts before any circuit), the IPPE first pose."""
    if camera.size is not None and (image.shape[1], image.shape[0]) != camera.size:
        raise InputError(f"image: {image.shape[1]}x{image.shape[0]} pixels but the camera "
                         f"file is for {camera.size[0]}x{camera.size[1]}")
    matched = match(detect(image, tagmap.family), tagmap, max_tags)
    problem = Problem(K=camera.K, dist=camera.dist, points2d=matched.points2d,
                      points3d=matched.points3d,
                      initial_pose=initial_pose(matched, tagmap, camera),
                      image_size=camera.size)
    return problem, matched
