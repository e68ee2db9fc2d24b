"""The Python API for a robot's own code (a ROS node, a drone's control loop): open the
servers once, localize frame after frame, keep the connections.

    from snail_client.api import Localizer

    with Localizer(camera="cam.json", tag_map="map.json") as loc:  # servers on loopback
        for image in camera_frames():
            pose = loc.localize_image(image)          # seeded by the last trusted pose
            if pose.trusted:
                print(pose.rvec, pose.tvec, pose.record["invocations"])

Give ``garbler=``, ``evaluator=`` and ``tls_dir=`` for remote servers. A frame localized
on its own makes at least ``min_invocations`` secure runs (padding included): its iteration
count never reaches the servers. A stream follows the camera at its rate with
``Localizer.track``, on the same fixed schedule as ``snail-client track``:

    with Localizer(camera="cam.json", tag_map="map.json") as loc:
        for pose in loc.track(camera_frames()):      # one secure run a frame after the first
            print(pose.status, pose.record["latency_s"], pose.record["track_status"])
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from snail_common.loc.problem import PoseVectors, Problem, ProblemError
from snail_common.loc.trust import TRUSTED

from .inputs.apriltag import problem_from_image, read_image
from .inputs.camera import Camera, load_camera
from .inputs.tagmap import TagMap, load_tagmap
from .localize import Options, backend_for, localize
from .track_frames import Problems
from .tracking import Item, Tracker

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
        """Converged, or (a tracked frame) every check passed on its fixed runs."""
        return self.status in TRUSTED

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
        problem = self.points_problem(points2d, points3d, initial or self.last, camera)
        return self.localize_problem(problem, initial)

    def points_problem(self, points2d: np.ndarray, points3d: np.ndarray,
                       initial: PoseVectors | None = None,
                       camera: Camera | None = None) -> Problem:
        """The problem of matched pixels and map points, starting at ``initial`` or (computed
        here in the clear) IPPE for points on one plane, else EPnP."""
        camera = camera or self.camera
        if camera is None:
            raise ValueError("camera: needed to localize points")
        p2 = np.asarray(points2d, np.float64).reshape(-1, 2)
        p3 = np.asarray(points3d, np.float64).reshape(-1, 3)
        if len(p2) != len(p3) or len(p2) < 4:
            raise ProblemError(f"points2d: {len(p2)} points for {len(p3)} map points "
                               "(at least 4 matched pairs are needed)")
        start = initial or first_pose(p2, p3, camera)
        return Problem(K=camera.K, dist=camera.dist, points2d=p2, points3d=p3,
                       initial_pose=start, image_size=camera.size)

    def localize_problem(self, problem: Problem, initial: PoseVectors | None = None,
                         tag_ids: tuple[int, ...] = ()) -> Pose:
        """Localize a built problem from ``initial`` or the last trusted pose."""
        record = localize(problem, self.options, self.backend, initial=initial or self.last)
        pose = Pose(np.array(record["rvec"]), np.array(record["tvec"]), record["status"],
                    record, tag_ids)
        if pose.trusted:
            self.last = PoseVectors(pose.rvec, pose.tvec)
        return pose

    def track(self, frames: Iterable[Any], motion: Motion = None) -> Iterator[Pose]:
        """Follow a stream privately on the fixed schedule: one ``Pose`` per frame, in
        order, each as soon as it and those before it are back.

        The first frame gets a padded localization (``min_invocations`` secure runs, from
        ``initial`` as ``localize_*`` take it, or the frame's own first pose); every later
        one exactly ``runs_per_frame`` runs (a Localizer option, default 1), each one
        Gauss-Newton step (``step="lm"`` damps it) from the prediction: the last trusted
        pose, moved by ``motion`` when given, else by the ``motion_model`` (``"auto"``:
        the motion between the last two answers while that has predicted better). The
        servers see the same circuit and count for every frame whatever the data: a lost
        frame (RMS above ``max_rms_px``, points behind the camera) is re-localized within
        the later frames' own runs. With ``in_flight`` D, D frames' runs overlap (each
        starts from the pose of the frame D before it); ``rate`` R runs R secure runs a
        second whatever the frames.

        Args:
            frames: camera images (arrays or file names; needs ``camera`` and
                ``tag_map``), built ``Problem``s, or ``(points2d, points3d)`` pairs (needs
                ``camera``). Taken one at a time, when the tracker is ready for them: a
                generator may wait for its camera, or (a closed loop) act on the last pose
                before it makes the next frame.
            motion: the camera's motion since the previous frame, for each frame: an
                iterable beside ``frames`` or a function of the frame's index (None:
                not known). A motion M maps the previous world-to-camera pose to the next
                (``snail_common.loc.schedule.compose``); ``schedule.relative(before,
                after)`` makes one from two odometry poses.

        Yields:
            Pose: ``status`` ``converged`` (the first frame), ``tracked`` (a later frame
            whose answer passed every check), a reason it is not trusted, or ``failed``
            (the frame could not be used, e.g. no tag in view: rvec and tvec are NaN, and
            its runs were padding). ``record`` has the frame's ``runs``, ``latency_s``
            (handed in to pose out), ``track_status`` (tracking, lost, relocalized) and
            ``revealed``.
        """
        builders: deque[_Built] = deque()
        motion_of = _motions(motion)

        def items() -> Iterator[Item]:
            for index, frame in enumerate(frames):
                built = _Built(self, frame, self.last if index == 0 else None)
                builders.append(built)
                yield Item(f"[{index}]", built, motion_of(index))

        solver = Problems(self.options)
        for out, _ in Tracker(self.options, self.backend, solver).run(items()):
            built = builders.popleft()
            if "failure" in out:
                nan = np.full(3, np.nan)
                yield Pose(nan, nan.copy(), "failed", out, built.tag_ids)
                continue
            pose = Pose(np.array(out["rvec"]), np.array(out["tvec"]), out["status"], out,
                        built.tag_ids)
            if pose.trusted:
                self.last = PoseVectors(pose.rvec, pose.tvec)
            yield pose

    def reset(self) -> None:
        """Forget the last pose (the robot was moved): the next frame starts afresh."""
        self.last = None

    def close(self) -> None:
        self._stack.close()

    def __enter__(self) -> Localizer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


Motion = Iterable[PoseVectors | None] | Callable[[int], PoseVectors | None] | None


def _motions(motion: Motion) -> Callable[[int], PoseVectors | None]:
    """Frame index -> the camera's motion before it, from either form ``track`` takes."""
    if motion is None:
        return lambda _: None
    if callable(motion):
        return motion
    source = iter(motion)
    return lambda _: next(source, None)


class _Built:
    """Builds one frame of ``Localizer.track`` into a problem when the tracker takes it
    (detection is part of the frame's latency), keeping the tags it saw."""

    def __init__(self, loc: Localizer, frame: Any, initial: PoseVectors | None) -> None:
        self.loc, self.frame, self.initial = loc, frame, initial
        self.tag_ids: tuple[int, ...] = ()

    def __call__(self) -> Problem:
        loc, frame = self.loc, self.frame
        if isinstance(frame, Problem):
            problem = frame
        elif isinstance(frame, tuple) and len(frame) == 2:
            problem = loc.points_problem(*frame, initial=self.initial)
        else:
            if loc.camera is None or loc.tag_map is None:
                raise ValueError("camera and tag_map: needed to track images")
            image = frame if isinstance(frame, np.ndarray) else read_image(frame)
            problem, matched = problem_from_image(image, loc.tag_map, loc.camera,
                                                  loc.max_tags)
            self.tag_ids = tuple(matched.tag_ids)
        if self.initial is not None:
            problem = dataclasses.replace(problem, initial_pose=self.initial)
        return problem


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
