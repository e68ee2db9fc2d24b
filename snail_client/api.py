"""The Python API for a robot's own code (a ROS node, a drone's control loop): open the
servers once, localize frame after frame, keep the connections.

    from snail_client.api import Localizer

    with Localizer(camera="cam.json", tag_map="map.json") as loc:  # servers on loopback
        for image in camera_frames():
            pose = loc.localize_image(image)          # seeded by the last trusted pose
            if pose.trusted:
                print(pose.rvec, pose.tvec, pose.record["invocations"])

Give ``garbler=``, ``evaluator=`` and ``tls_dir=`` for remote servers. Every frame makes at
least ``min_invocations`` secure runs (padding included), the same policy as
``snail-client track``: a frame's iteration count never reaches the servers.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from snail_common.loc.problem import PoseVectors, Problem, ProblemError

from .inputs.apriltag import problem_from_image, read_image
from .inputs.camera import Camera, load_camera
from .inputs.tagmap import TagMap, load_tagmap
from .localize import Options, backend_for, localize

_PLANAR = 1e-6  # smallest / largest spread of the map points below this: one plane


@dataclass(frozen=True)
class Pose:
    """One frame's answer: world-to-camera rvec/tvec (OpenCV's convention), whether it can
    be trusted (``status`` is ``converged``), and the whole snail-result/1 record."""

    rvec: np.ndarray
    tvec: np.ndarray
    status: str
    record: dict
    tag_ids: tuple[int, ...] = ()  # the mapped tags seen (image frames)

    @property
    def trusted(self) -> bool:
        return self.status == "converged"

    @property
    def camera_position(self) -> np.ndarray:
        """The camera centre in world coordinates."""
        R, _ = cv2.Rodrigues(self.rvec)
        return -R.T @ self.tvec


class Localizer:
    """A session with the two servers for a stream of frames (see the module's example).

    ``camera`` and ``tag_map`` (objects or file paths) are needed for images; ``max_tags``
    keeps the largest tags in view (with ``pad_points=4 * max_tags`` every frame has the
    same number of points: one circuit, and the servers cannot count the tags); options
    are the command line's (``backend``, ``algorithm``, ``min_invocations``, ...).
    """

    def __init__(self, camera: Camera | str | Path | None = None,
                 tag_map: TagMap | str | Path | None = None, max_tags: int | None = None,
                 **options: object) -> None:
        self.camera = load_camera(camera) if isinstance(camera, (str, Path)) else camera
        self.tag_map = load_tagmap(tag_map) if isinstance(tag_map, (str, Path)) else tag_map
        self.max_tags = max_tags
        self.options = Options(**options)  # ValueError naming a bad option
        self._stack = contextlib.ExitStack()
        self.backend = self._stack.enter_context(backend_for(self.options))
        self.last: PoseVectors | None = None  # the last trusted pose, seeding the next

    def localize_image(self, image: np.ndarray | str | Path,
                       initial: PoseVectors | None = None) -> Pose:
        """Detect the map's tags in ``image`` (an array or a file) and localize. The start
        is ``initial``, else the last trusted pose, else IPPE on the largest tag.
        InputError (a ProblemError) when no mapped tag is seen."""
        if self.camera is None or self.tag_map is None:
            raise ValueError("camera and tag_map: needed to localize images")
        if not isinstance(image, np.ndarray):
            image = read_image(image)
        problem, matched = problem_from_image(image, self.tag_map, self.camera,
                                              self.max_tags)
        return self.localize_problem(problem, initial, tuple(matched.tag_ids))

    def localize_points(self, points2d: np.ndarray, points3d: np.ndarray,
                        initial: PoseVectors | None = None,
                        camera: Camera | None = None) -> Pose:
        """Localize from matched pixels (n, 2) and map points (n, 3). Without ``initial``
        or a last pose, the start is computed here in the clear (IPPE for points on one
        plane, else EPnP)."""
        camera = camera or self.camera
        if camera is None:
            raise ValueError("camera: needed to localize points")
        p2 = np.asarray(points2d, np.float64).reshape(-1, 2)
        p3 = np.asarray(points3d, np.float64).reshape(-1, 3)
        if len(p2) != len(p3) or len(p2) < 4:
            raise ProblemError(f"points2d: {len(p2)} points for {len(p3)} map points "
                               "(at least 4 matched pairs are needed)")
        start = initial or self.last or first_pose(p2, p3, camera)
        problem = Problem(K=camera.K, dist=camera.dist, points2d=p2, points3d=p3,
                          initial_pose=start, image_size=camera.size)
        return self.localize_problem(problem, initial)

    def localize_problem(self, problem: Problem, initial: PoseVectors | None = None,
                         tag_ids: tuple[int, ...] = ()) -> Pose:
        """Localize a built problem from ``initial`` or the last trusted pose."""
        record = localize(problem, self.options, self.backend, initial=initial or self.last)
        pose = Pose(np.array(record["rvec"]), np.array(record["tvec"]), record["status"],
                    record, tag_ids)
        if pose.trusted:
            self.last = PoseVectors(pose.rvec, pose.tvec)
        return pose

    def reset(self) -> None:
        """Forget the last pose (the robot was moved): the next frame starts afresh."""
        self.last = None

    def close(self) -> None:
        self._stack.close()

    def __enter__(self) -> Localizer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def first_pose(points2d: np.ndarray, points3d: np.ndarray, camera: Camera) -> PoseVectors:
    """A closed-form start in the clear: IPPE when the map points lie on one plane
    (EPnP is unstable there), EPnP otherwise."""
    spread = np.linalg.svd(points3d - points3d.mean(axis=0), compute_uv=False)
    planar = spread[2] <= _PLANAR * spread[0]
    flag = cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_EPNP
    ok, rvec, tvec = cv2.solvePnP(points3d, points2d, camera.K, camera.dist, flags=flag)
    if not ok:
        raise ProblemError("points2d: no first pose for these matches")
    return PoseVectors(rvec.reshape(3), tvec.reshape(3))
