"""Turbo the snail: a differential-drive robot that drives to a target pose by
position-based visual servoing on private localization, as in the Snail paper's proof of
concept.

The room has printed AprilTags on its walls; the robot's camera sees them (rendered from
the robot's true pose with blur, noise and lens distortion). At every control step the
robot moves at most 0.1 m (the paper's robot re-localized every 0.1 m), takes an image and
localizes privately through the two servers, seeded by its last estimate moved by the
commanded motion (odometry); the polar-coordinate controller (Astolfi) then steers the
estimate to the target, and a final turn fixes the heading. The wheels slip a little, so
odometry alone would drift.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from snail_client.api import Localizer, Pose
from snail_client.inputs.fields import InputError
from snail_common.loc.problem import PoseVectors
from snail_sim.turbo_world import (  # noqa: F401  (re-exported: the demo's names)
    CAMERA_HEIGHT,
    GOAL_M,
    GOAL_RAD,
    START,
    STEP_M,
    TARGET,
    TURN_RAD,
    RobotPose,
    control,
    robot_camera,
    room,
    wrap,
)

from .render import Look, render

SLIP = 0.03  # relative wheel slip (1 sigma)

@dataclass
class Run:
    """What happened, step by step (turbo.json) and for drawing."""

    steps: list[dict] = field(default_factory=list)
    true_path: list[RobotPose] = field(default_factory=list)
    estimates: list[RobotPose] = field(default_factory=list)


def _pose_json(pose: PoseVectors) -> dict:
    return {"rvec": [float(v) for v in pose.rvec], "tvec": [float(v) for v in pose.tvec]}


def drive(localizer: Localizer, start: RobotPose, target: RobotPose, max_steps: int,
          rng: np.random.Generator, look: Look, on_step=None) -> Run:
    """Servo from ``start`` to ``target``; ``on_step(run, image, pose)`` after each step."""
    run = Run()
    truth, seed = start, None
    began = time.perf_counter()
    for _ in range(max_steps):
        image = render(localizer.tag_map, localizer.camera, truth.camera(), look, rng)
        cpu, wall = time.process_time(), time.perf_counter()
        traffic_before = _bytes(localizer)
        try:
            pose: Pose | None = localizer.localize_image(
                image, initial=None if seed is None else seed.camera())
        except InputError:
            pose = None  # no tag in view: carry on with odometry
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
        trusted = pose is not None and pose.trusted
        estimate = RobotPose.from_camera(pose.rvec, pose.tvec) if trusted else seed
        if estimate is None:
            raise RuntimeError("no tag in view at the start: cannot localize")
        distance, turn, reached = control(estimate, target)
        step = {
            "t": round(time.perf_counter() - began, 3),
            "true": _pose_json(truth.camera()), "estimate": _pose_json(estimate.camera()),
            "robot_true": [truth.x, truth.y, math.degrees(truth.heading)],
            "robot_estimate": [estimate.x, estimate.y, math.degrees(estimate.heading)],
            "status": pose.status if pose is not None else "no_tag",
            "tags": list(pose.tag_ids) if pose is not None else [],
            "iterations": pose.record["iterations"] if pose is not None else 0,
            "invocations": pose.record["invocations"] if pose is not None else 0,
            "seconds": wall, "bytes": _bytes(localizer) - traffic_before,
            "client_cpu_s": cpu,
            "position_error_m": math.hypot(estimate.x - truth.x, estimate.y - truth.y),
            "command": {"distance_m": distance, "turn_deg": math.degrees(turn)},
        }
        run.steps.append(step)
        run.true_path.append(truth)
        run.estimates.append(estimate)
        if on_step is not None:
            on_step(run, image, pose)
        if reached:
            break
        slip = 1 + rng.normal(scale=SLIP, size=2)
        truth = truth.moved(distance * slip[0], turn * slip[1])
        seed = estimate.moved(distance, turn)  # odometry: what was commanded
    return run


def _bytes(localizer: Localizer) -> int:
    return int(sum(localizer.backend.traffic().values()))


def summary(run: Run, target: RobotPose) -> dict:
    """The final errors against the target, from the true pose."""
    last = run.true_path[-1]
    position = math.hypot(last.x - target.x, last.y - target.y)
    rotation = abs(math.degrees(wrap(last.heading - target.heading)))
    later = run.steps[1:]
    return {"position_error_m": position, "rotation_error_deg": rotation,
            "reached": position <= 0.02 and rotation <= 2.0, "steps": len(run.steps),
            "median_seconds_per_step": float(np.median([s["seconds"] for s in run.steps])),
            "median_invocations_after_first": float(np.median(
                [s["invocations"] for s in later])) if later else None,
            "median_iterations_after_first": float(np.median(
                [s["iterations"] for s in later])) if later else None,
            "median_client_cpu_s": float(np.median([s["client_cpu_s"] for s in run.steps])),
            "total_bytes": int(sum(s["bytes"] for s in run.steps))}
