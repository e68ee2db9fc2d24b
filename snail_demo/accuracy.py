"""How often the image path's private pose matches OpenCV on the same detections.

A frame: a random tag scene (snail_demo.scenes) rendered with blur, noise and lens
distortion; the client detects, matches and starts from IPPE as ``localize --image``
does; the pose comes from the chosen backend (``cleartext`` is the garbled circuit's
exact output: garbled runs are bit-identical to it) and is compared with
``cv2.solvePnP`` (iterative LM) from the same first pose on the same detections, and with
the true pose. The issue's bar: within 0.5 % of the camera distance and 0.5 degrees.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from snail_client.inputs.apriltag import Matched, problem_from_image
from snail_client.inputs.fields import InputError
from snail_client.localize import Backend, Options, localize
from snail_common.loc.geometry import so3_exp
from snail_common.loc.problem import PoseVectors, Problem
from snail_common.loc.trust import pose_error

from .render import render
from .scenes import TagScene, random_tag_scene

POSITION_FRAC = 0.005
ROTATION_DEG = 0.5


@dataclass(frozen=True)
class FrameCheck:
    """One frame's pose against OpenCV and against the truth (position errors as a fraction
    of the distance from the camera to the matched corners' centroid)."""

    tags: int
    obliquity_deg: float
    status: str
    iterations: int
    opencv_position: float
    opencv_rotation_deg: float
    truth_position: float
    truth_rotation_deg: float

    @property
    def matches_opencv(self) -> bool:
        return (self.opencv_position <= POSITION_FRAC
                and self.opencv_rotation_deg <= ROTATION_DEG)


def opencv_pose(problem: Problem) -> PoseVectors:
    """cv2.solvePnP (iterative) on the problem's matches from its initial pose."""
    start = problem.initial_pose
    _, rvec, tvec = cv2.solvePnP(problem.points3d, problem.points2d, problem.K, problem.dist,
                                 start.rvec.copy(), start.tvec.copy(), useExtrinsicGuess=True,
                                 flags=cv2.SOLVEPNP_ITERATIVE)
    return PoseVectors(rvec.reshape(3), tvec.reshape(3))


def _relative(rvec: np.ndarray, tvec: np.ndarray, against: PoseVectors,
              points3d: np.ndarray) -> tuple[float, float]:
    err = pose_error(np.asarray(rvec), np.asarray(tvec), against)
    distance = np.linalg.norm(so3_exp(against.rvec) @ points3d.mean(axis=0) + against.tvec)
    return err["translation"] / distance, err["rotation_deg"]


def check_frame(scene: TagScene, options: Options, backend: Backend,
                rng: np.random.Generator) -> tuple[FrameCheck, Matched] | None:
    """The frame's check, or None when no mapped tag was detected."""
    image = render(scene.tagmap, scene.camera, scene.pose, scene.look, rng)
    try:
        problem, matched = problem_from_image(image, scene.tagmap, scene.camera)
    except InputError:
        return None
    record = localize(problem, options, backend)
    cv_pos, cv_rot = _relative(record["rvec"], record["tvec"], opencv_pose(problem),
                               problem.points3d)
    true_pos, true_rot = _relative(record["rvec"], record["tvec"], scene.pose,
                                   problem.points3d)
    return FrameCheck(len(matched.tag_ids), scene.obliquity_deg, record["status"],
                      record["iterations"], cv_pos, cv_rot, true_pos, true_rot), matched


def sweep(frames: int, seed: int, options: Options, backend: Backend,
          progress: object = None) -> dict:
    """``frames`` random scenes: how many were detected, how many matched OpenCV, and the
    error percentiles against OpenCV and the truth."""
    rng = np.random.default_rng(seed)
    checks: list[FrameCheck] = []
    missed = 0
    for _ in range(frames):
        out = check_frame(random_tag_scene(rng), options, backend, rng)
        if out is None:
            missed += 1
        else:
            checks.append(out[0])
        if progress is not None:
            progress.update(1)
    matched = sum(c.matches_opencv for c in checks)
    table = {k: np.array([asdict(c)[k] for c in checks]) for k in (
        "opencv_position", "opencv_rotation_deg", "truth_position", "truth_rotation_deg")}
    return {
        "frames": frames, "detected": len(checks), "not_detected": missed,
        "matches_opencv": matched,
        "fraction_matching_opencv": matched / len(checks) if checks else 0.0,
        "converged": sum(c.status == "converged" for c in checks),
        "percentiles": {k: {p: float(np.percentile(v, int(p[1:]))) for p in ("p50", "p99")}
                        | {"max": float(v.max())} for k, v in table.items()} if checks else {},
        "failures": [asdict(c) for c in checks if not c.matches_opencv],
        "backend": options.backend, "seed": seed,
    }
