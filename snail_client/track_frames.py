"""What a tracker's frame is and how it is solved, in each setting: ``Problems`` (the
device holds its 2D-3D matches: snail-problem/1, images) and ``MapFrames`` (the map-owner
setting: snail-frame/1, the map points stay with the map owner).

A solver turns a frame and the schedule's plan into a snail-result/1 record: the padded
localization of today (the first frame) or exactly the plan's runs from its start
(``track_frame``), and says whether the answer fit better than its start (worth
continuing from while lost). ProblemError: nothing could run for this frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from snail_common.loc.backends import Backend
from snail_common.loc.mapfile import Frame
from snail_common.loc.owner import PublishedMap, localize_known
from snail_common.loc.problem import PoseVectors, Problem, ProblemError, check_in_front
from snail_common.loc.reference import reprojection_rms
from snail_common.loc.schedule import Plan
from snail_common.pnp.spec import Spec

from .localize import MAX_IN_FLIGHT, Options, localize, track_frame
from .mapowner import MapOwnerLink
from .owner_localize import MAP_OWNER_LINKS, record, run_frame
from .sessions import LINKS


@dataclass
class Solved:
    record: dict
    spec: Spec | None
    pose: PoseVectors | None
    improved: bool
    built: Any = None  # what the source became (a Problem or Frame), for the caller


class Problems:
    """The offload setting: frames are snail-problem/1 (the device holds the points), so
    a frame's answer is checked in the clear (its reprojection RMS)."""

    max_in_flight = MAX_IN_FLIGHT
    warmup = 0  # any pose is checked here: no frame needs a second run for its verdict

    def __init__(self, options: Options) -> None:
        self.options = options

    def spec(self, problem: Problem) -> Spec:
        return self.options.spec(problem.n)

    def solve(self, problem: Problem, plan: Plan, backend: Backend) -> Solved:
        start = _in_front(problem, plan.start) or _in_front(problem, problem.initial_pose)
        if start is None:
            raise ProblemError("no start with every point in front of the camera (the "
                               "prediction and the frame's initial pose)")
        if plan.padded or self.options.mode == "do":
            out = localize(problem, self.options, backend, initial=start)
        else:
            out = track_frame(problem, self.options, backend, start, plan.runs)
        pose = PoseVectors(np.array(out["rvec"]), np.array(out["tvec"]))
        improved = bool(out["rms_px"] < reprojection_rms(problem, start.rvec, start.tvec))
        return Solved(out, self.spec(problem), pose, improved, problem)


def _in_front(problem: Problem, pose: PoseVectors | None) -> PoseVectors | None:
    if pose is None:
        return None
    try:
        check_in_front(problem, pose)
    except ProblemError:
        return None
    return pose


class MapFrames:
    """The map-owner setting: each frame's points selected from the map owner by OT
    (mapowner.py), its runs on the map-owner circuit. The device holds no 3D point: its
    checks are the cost's, at the last pose a run evaluated. Frames overlap as in the
    offload setting: each run names its own frame to the map owner (owner_pads.py).
    The first two tracked frames get two runs (``Schedule`` warm-up, fixed in advance):
    predicted before any motion is known, their one run's fit is the prediction's, not
    the answer's, and judged them lost though their answers were right."""

    max_in_flight = MAX_IN_FLIGHT
    warmup = 2

    def __init__(self, options: Options, link: MapOwnerLink | None,
                 known: tuple[PublishedMap, np.ndarray] | None = None) -> None:
        self.options, self.link, self.known = options, link, known

    def spec(self, frame: Frame) -> Spec:
        o = self.options
        return Spec(o.algorithm, "sil", o.solver, frame.n, owner=self.link is not None,
                    arith=o.arith_used)

    def solve(self, frame: Frame, plan: Plan, backend: Backend) -> Solved:
        start = plan.start or frame.initial_pose
        if start is None:
            raise ProblemError("initial_pose: missing (the first frame needs one)")
        runs = None if plan.padded else plan.runs
        if self.link is None:  # --map in the clear: the points are known here
            published, values = self.known
            out = record(localize_known(frame, published, values, self.options, backend,
                                        start, runs), self.options,
                         dict.fromkeys((*LINKS, *MAP_OWNER_LINKS), 0), tracked=bool(runs))
        else:
            out = run_frame(frame, self.link, backend, self.options, start, runs)
        pose = PoseVectors(np.array(out["rvec"]), np.array(out["tvec"]))
        # with one run the cost known is the start's: a finite answer is the best guess
        improved = math.isfinite(out["rms_px"]) and bool(np.isfinite(pose.tvec).all())
        return Solved(out, self.spec(frame), pose, improved, frame)

