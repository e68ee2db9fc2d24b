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
from snail_client.inputs.camera import Camera, intrinsics
from snail_client.inputs.fields import InputError
from snail_client.inputs.tagmap import Tag, TagMap
from snail_common.loc.geometry import rvec_from_matrix, so3_exp
from snail_common.loc.problem import PoseVectors

from .render import Look, render

CAMERA_HEIGHT = 0.12  # metres above the floor
STEP_M = 0.1  # at most this far between two localizations
TURN_RAD = math.radians(15)  # and at most this much turning
GOAL_M, GOAL_RAD = 0.01, math.radians(1.0)  # the estimate is at the target within these
K_RHO, K_ALPHA, K_BETA = 0.8, 1.0, -0.4  # polar controller gains (per step)
SLIP = 0.03  # relative wheel slip (1 sigma)


@dataclass(frozen=True)
class RobotPose:
    x: float
    y: float
    heading: float  # radians, 0 along +x, counter-clockwise

    def camera(self) -> PoseVectors:
        """World-to-camera pose of the forward-looking camera (z forward, y down)."""
        c, s = math.cos(self.heading), math.sin(self.heading)
        to_world = np.column_stack([[s, -c, 0.0], [0.0, 0.0, -1.0], [c, s, 0.0]])
        R = to_world.T
        centre = np.array([self.x, self.y, CAMERA_HEIGHT])
        return PoseVectors(rvec_from_matrix(R), -R @ centre)

    @staticmethod
    def from_camera(rvec: np.ndarray, tvec: np.ndarray) -> RobotPose:
        R = so3_exp(np.asarray(rvec, np.float64))
        centre = -R.T @ np.asarray(tvec, np.float64)
        forward = R[2]  # the optical axis in world coordinates
        return RobotPose(float(centre[0]), float(centre[1]),
                         math.atan2(forward[1], forward[0]))

    def moved(self, distance: float, turn: float) -> RobotPose:
        """Turn half, drive, turn half (a short arc)."""
        mid = self.heading + turn / 2
        return RobotPose(self.x + distance * math.cos(mid), self.y + distance * math.sin(mid),
                         _wrap(self.heading + turn))


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def room() -> TagMap:
    """Ten 10 cm tags: six on the far wall (x = 2.2 m), two on each side wall."""
    tags: dict[int, Tag] = {}
    size = 0.10
    walls = [  # (tag-to-world rotation as columns x_tag, y_tag, z_tag; centres)
        (np.column_stack([[0, -1, 0], [0, 0, 1], [-1, 0, 0]]),
         [(2.2, y, z) for y, z in zip((-0.75, -0.45, -0.15, 0.15, 0.45, 0.75),
                                      (0.14, 0.22, 0.14, 0.22, 0.14, 0.22))]),
        (np.column_stack([[1, 0, 0], [0, 0, 1], [0, -1, 0]]),
         [(1.2, 1.0, 0.16), (1.7, 1.0, 0.16)]),
        (np.column_stack([[-1, 0, 0], [0, 0, 1], [0, 1, 0]]),
         [(1.2, -1.0, 0.16), (1.7, -1.0, 0.16)]),
    ]
    tag_id = 0
    for rotation, centres in walls:
        for centre in centres:
            tags[tag_id] = Tag(tag_id, size, rvec_from_matrix(rotation.astype(float)),
                               np.array(centre, float))
            tag_id += 7  # spread over the family
    return TagMap("tag36h11", tags)


def robot_camera() -> Camera:
    """A small wide-angle camera with barrel distortion."""
    return Camera(intrinsics(420.0, 420.0, 319.5, 239.5),
                  np.array([-0.12, 0.03, 5e-4, -3e-4, 0.0]), (640, 480))


def control(estimate: RobotPose, target: RobotPose) -> tuple[float, float, bool]:
    """(distance, turn) for the next step, and whether the estimate is at the target."""
    dx, dy = target.x - estimate.x, target.y - estimate.y
    rho = math.hypot(dx, dy)
    heading_error = _wrap(target.heading - estimate.heading)
    if rho < GOAL_M:
        if abs(heading_error) < GOAL_RAD:
            return 0.0, 0.0, True
        return 0.0, float(np.clip(heading_error, -TURN_RAD, TURN_RAD)), False
    alpha = _wrap(math.atan2(dy, dx) - estimate.heading)
    beta = _wrap(target.heading - math.atan2(dy, dx))
    if rho < 3 * GOAL_M:  # close: creep straight at it, no more arcs
        beta = 0.0
    distance = min(K_RHO * rho, STEP_M) * (1 if abs(alpha) < math.pi / 2 else -1)
    turn = float(np.clip(K_ALPHA * alpha + K_BETA * beta, -TURN_RAD, TURN_RAD))
    return distance, turn, False


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
    rotation = abs(math.degrees(_wrap(last.heading - target.heading)))
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
