"""Turbo's world: the room of printed AprilTags, the robot's camera, its kinematics and
its controller (polar coordinates, Astolfi), as the Snail paper's proof of concept drove.

``snail-demo turbo`` renders this room and drives in it on private poses;
``snail-bench track --sequence turbo`` follows the same drive at a camera's rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from snail_client.inputs.camera import Camera, intrinsics
from snail_client.inputs.tagmap import Tag, TagMap
from snail_common.loc.geometry import rvec_from_matrix, so3_exp
from snail_common.loc.problem import PoseVectors

CAMERA_HEIGHT = 0.12  # metres above the floor
STEP_M = 0.1  # at most this far between two localizations
TURN_RAD = math.radians(15)  # and at most this much turning
GOAL_M, GOAL_RAD = 0.01, math.radians(1.0)  # the estimate is at the target within these
K_RHO, K_ALPHA, K_BETA = 0.8, 1.0, -0.4  # polar controller gains (per step)


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
                         wrap(self.heading + turn))


def wrap(angle: float) -> float:
    """An angle in [-pi, pi)."""
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
    heading_error = wrap(target.heading - estimate.heading)
    if rho < GOAL_M:
        if abs(heading_error) < GOAL_RAD:
            return 0.0, 0.0, True
        return 0.0, float(np.clip(heading_error, -TURN_RAD, TURN_RAD)), False
    alpha = wrap(math.atan2(dy, dx) - estimate.heading)
    beta = wrap(target.heading - math.atan2(dy, dx))
    if rho < 3 * GOAL_M:  # close: creep straight at it, no more arcs
        beta = 0.0
    distance = min(K_RHO * rho, STEP_M) * (1 if abs(alpha) < math.pi / 2 else -1)
    turn = float(np.clip(K_ALPHA * alpha + K_BETA * beta, -TURN_RAD, TURN_RAD))
    return distance, turn, False


START = RobotPose(0.35, -0.55, math.radians(35))
TARGET = RobotPose(1.6, 0.25, 0.0)
