"""Camera sequences made by the project, for ``snail-bench track`` and the tests.

- ``handheld``: a hand-held camera (640x480, f = 600 px) carried at walking pace around an
  8 x 6 x 3 m room whose walls, floor, ceiling and a few boxes carry ``map_points``
  points. The path is an ellipse at chest height with a walker's bob; the camera looks at
  the walls, its yaw, pitch and roll swaying slowly, plus hand shake (a random walk of a
  few tenths of a degree). At 30 frames/s and 1 m/s a frame moves 3 cm and turns about a
  degree: what a phone sees. Each frame keeps the points of the frame before it that are
  still in view (feature tracks) and fills up to ``points`` with others in view.
- ``turbo``: Turbo's drive (turbo_world.py) at a camera's rate: the robot drives by its
  controller from START to TARGET at ``speed`` m/s (turning at most ``turn_deg_s``), then
  backs up along the same path to START, and again; it sees the room's tags through its
  distorted wide-angle camera, and each frame's points are up to ``points`` corners of the
  largest tags fully in view, all four of a tag before the next (detector noise on the
  corners).

Pixel noise is Gaussian, ``noise_px`` (1 sigma) on every observation, and correlated in
time as a tracked feature's is: each point's error drifts (an AR(1) process) by about
``jitter_px`` a frame rather than being drawn afresh. Fresh noise on every frame would make
the best pose of a frame jump by a degree or more at n = 6 from one frame to the next,
which a camera does not do: its features are the same from frame to frame.

Frame 0 carries an initial pose 2 degrees and 5 cm off the truth; every frame carries the
truth as ``reference_pose``. ``ids`` says which map points each frame saw (the map-owner
setting's ``map_ids``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from snail_common.loc.geometry import rvec_from_matrix, so3_exp
from snail_common.loc.problem import PoseVectors, Problem
from snail_common.loc.schedule import relative

from .turbo_world import START, TARGET, RobotPose, control, robot_camera, room

SEQUENCES = ("handheld", "turbo")
HANDHELD_SIZE = (640, 480)
HANDHELD_F = 600.0
ROOM = np.array([[-4.0, -3.0, 0.0], [4.0, 3.0, 3.0]])  # the room's corners, metres
MARGIN_PX = 8
SLIP = 0.03  # Turbo's wheel slip, relative (1 sigma): its odometry's error
NEAREST_M = 0.3
DIAGONAL_FIRST = (0, 2, 1, 3)  # a tag's corners, in the order a partial tag gives them
SPREAD_DRAWS = 8  # candidates drawn for each new feature, the farthest from the others kept


@dataclass(frozen=True)
class Sequence:
    """Frames of one made-up camera: ``problems[i]`` has frame i's matches (``None``:
    nothing in view), ``ids[i]`` the indices of its points in ``world``."""

    name: str
    fps: float
    problems: list[Problem | None]
    world: np.ndarray  # (M, 3): the map
    ids: list[np.ndarray]
    # the camera's motion before each frame as odometry measured it (Turbo's wheels,
    # slipping 3 %), to pass to Localizer.track(motion=...); None: no odometry
    motions: list[PoseVectors | None] | None = None


def _room_points(rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` points on the room's six faces (by area) and on five boxes in it."""
    lo, hi = ROOM
    boxes = [(rng.uniform([-3, -2, 0], [2, 1, 0]), rng.uniform([0.4, 0.4, 0.4], [1, 1, 1.2]))
             for _ in range(5)]
    faces = [(lo, hi)] + [(c, c + s) for c, s in boxes]
    areas = np.array([2 * ((b - a)[0] * (b - a)[1] + (b - a)[1] * (b - a)[2]
                           + (b - a)[0] * (b - a)[2]) for a, b in faces])
    which = rng.choice(len(faces), size=count, p=areas / areas.sum())
    out = np.empty((count, 3))
    for i, face in enumerate(which):
        a, b = faces[face]
        point = rng.uniform(a, b)
        axis = rng.choice(3, p=_face_weights(b - a))
        point[axis] = a[axis] if rng.random() < 0.5 else b[axis]
        out[i] = point
    return out


def _face_weights(size: np.ndarray) -> np.ndarray:
    """Of a box, the share of its surface on the faces normal to each axis."""
    w = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]])
    return w / w.sum()


def _look(centre: np.ndarray, yaw: float, pitch: float, roll: float) -> PoseVectors:
    """World-to-camera pose of a camera at ``centre`` (z up in the world), looking along
    yaw/pitch (radians), rolled about its optical axis."""
    forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw),
                        math.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = so3_exp(np.array([0.0, 0.0, roll])) @ np.vstack([right, down, forward])
    return PoseVectors(rvec_from_matrix(R), -R @ centre)


def _start(rng: np.random.Generator, truth: PoseVectors) -> PoseVectors:
    """Frame 0's initial pose: 2 degrees and 5 cm off the truth (a relocalization's)."""
    axis = rng.normal(size=3)
    turn = so3_exp(axis / np.linalg.norm(axis) * math.radians(2.0))
    shift = rng.normal(size=3)
    return PoseVectors(rvec_from_matrix(turn @ so3_exp(truth.rvec)),
                       truth.tvec + 0.05 * shift / np.linalg.norm(shift))


class _Drift:
    """Each point's pixel error: stationary N(0, sigma^2), moving ~``jitter`` a frame."""

    def __init__(self, rng: np.random.Generator, count: int, sigma: float,
                 jitter: float) -> None:
        self.rng, self.sigma = rng, sigma
        self.rho = max(0.0, 1.0 - jitter ** 2 / (2 * sigma ** 2)) if sigma else 0.0
        self.error = rng.normal(scale=sigma, size=(count, 2))

    def step(self) -> np.ndarray:
        fresh = self.rng.normal(scale=self.sigma * math.sqrt(1 - self.rho ** 2),
                                size=self.error.shape)
        self.error = self.rho * self.error + fresh
        return self.error


def handheld(rng: np.random.Generator, points: int, frames: int, fps: float = 30.0,
             speed: float = 0.5, noise_px: float = 0.5, jitter_px: float = 0.15,
             map_points: int = 4000, shake_deg: float = 0.3) -> Sequence:
    """The hand-held walk (see the module docstring); ``speed`` in m/s."""
    world = _room_points(rng, map_points)
    drift = _Drift(rng, map_points, noise_px, jitter_px)
    K = np.array([[HANDHELD_F, 0, 319.5], [0, HANDHELD_F, 239.5], [0, 0, 1.0]])
    dist = np.zeros(5)
    semi = np.array([2.2, 1.3])
    rate = speed / float(np.mean(semi))  # radians of the ellipse per second
    shake = np.zeros(3)
    problems: list[Problem | None] = []
    ids: list[np.ndarray] = []
    kept = np.zeros(0, np.int64)
    for k in range(frames):
        t = k / fps
        phase = rate * t
        centre = np.array([semi[0] * math.cos(phase), semi[1] * math.sin(phase),
                           1.4 + 0.02 * math.sin(2 * math.pi * 1.8 * t)])
        heading = math.atan2(semi[1] * math.cos(phase), -semi[0] * math.sin(phase))
        shake = 0.9 * shake + rng.normal(scale=math.radians(shake_deg) * 0.44, size=3)
        truth = _look(centre, heading - math.radians(70) + math.radians(20)
                      * math.sin(0.3 * t) + shake[0],
                      math.radians(-8 + 6 * math.sin(0.5 * t)) + shake[1],
                      math.radians(4 * math.sin(0.7 * t)) + shake[2])
        kept, problem = _frame(rng, world, kept, points, truth, K, dist, HANDHELD_SIZE,
                               drift.step())
        if problem is not None and k == 0:
            problem = _with_start(problem, _start(rng, truth))
        problems.append(problem)
        ids.append(kept.copy())
    return Sequence("handheld", fps, problems, world, ids)


def _visible(world: np.ndarray, pose: PoseVectors, K: np.ndarray, dist: np.ndarray,
             size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Which points are in view (in front, inside the image's margins), and where."""
    cam = world @ so3_exp(pose.rvec).T + pose.tvec
    front = cam[:, 2] > NEAREST_M
    pix = np.full((len(world), 2), -1.0)
    if front.any():
        proj, _ = cv2.projectPoints(world[front], pose.rvec, pose.tvec, K, dist)
        pix[front] = proj.reshape(-1, 2)
    width, height = size
    inside = front & (pix[:, 0] >= MARGIN_PX) & (pix[:, 0] <= width - 1 - MARGIN_PX) \
        & (pix[:, 1] >= MARGIN_PX) & (pix[:, 1] <= height - 1 - MARGIN_PX)
    return inside, pix


def _frame(rng: np.random.Generator, world: np.ndarray, kept: np.ndarray, points: int,
           truth: PoseVectors, K: np.ndarray, dist: np.ndarray, size: tuple[int, int],
           error: np.ndarray) -> tuple[np.ndarray, Problem | None]:
    """The points still tracked from the last frame, topped up with others in view, each
    the farthest in the image from those chosen among a few drawn at random (a feature
    detector spreads its features over the image)."""
    inside, pix = _visible(world, truth, K, dist, size)
    chosen = list(kept[inside[kept]][:points])
    others = np.flatnonzero(inside)
    others = others[~np.isin(others, chosen)]
    while len(chosen) < points and len(others):
        draw = rng.choice(others, size=min(SPREAD_DRAWS, len(others)), replace=False)
        if chosen:
            gap = np.min(np.linalg.norm(pix[draw][:, None] - pix[chosen][None], axis=2),
                         axis=1)
            pick = int(draw[int(np.argmax(gap))])
        else:
            pick = int(draw[0])
        chosen.append(pick)
        others = others[others != pick]
    chosen = np.array(chosen, np.int64)
    if len(chosen) < 4:
        return chosen, None
    observed = pix[chosen] + error[chosen]
    return chosen, Problem(K=K, dist=dist, points2d=observed, points3d=world[chosen],
                           initial_pose=None, reference_pose=truth, image_size=size)


def _with_start(problem: Problem, start: PoseVectors) -> Problem:
    return Problem(K=problem.K, dist=problem.dist, points2d=problem.points2d,
                   points3d=problem.points3d, initial_pose=start,
                   reference_pose=problem.reference_pose, image_size=problem.image_size)


def turbo(rng: np.random.Generator, points: int, frames: int, fps: float = 30.0,
          speed: float = 0.3, noise_px: float = 0.3, jitter_px: float = 0.1,
          turn_deg_s: float = 45.0) -> Sequence:
    """Turbo's drive (see the module docstring): ``points`` corners at most a frame."""
    tagmap, camera = room(), robot_camera()
    world = np.concatenate([t.corners_world() for t in tagmap.tags.values()])
    drift = _Drift(rng, len(world), noise_px, jitter_px)
    leg = _leg(speed / fps, math.radians(turn_deg_s) / fps)
    there_and_back = leg + leg[-2:0:-1]
    problems: list[Problem | None] = []
    ids: list[np.ndarray] = []
    motions: list[PoseVectors | None] = [None]
    for k in range(frames):
        truth = there_and_back[k % len(there_and_back)].camera()
        if k:
            moved = there_and_back[(k - 1) % len(there_and_back)].camera()
            motions.append(_odometry(rng, moved, truth))
        chosen = _largest_tags(world, truth, camera, points)
        error = drift.step()
        if len(chosen):
            proj, _ = cv2.projectPoints(world[chosen], truth.rvec, truth.tvec, camera.K,
                                        camera.dist)
            observed = proj.reshape(-1, 2) + error[chosen]
            problem = Problem(K=camera.K, dist=camera.dist, points2d=observed,
                              points3d=world[chosen], initial_pose=None,
                              reference_pose=truth, image_size=camera.size)
            problems.append(_with_start(problem, _start(rng, truth)) if k == 0 else problem)
        else:
            problems.append(None)
        ids.append(chosen)
    return Sequence("turbo", fps, problems, world, ids, motions)


def _odometry(rng: np.random.Generator, before: PoseVectors, after: PoseVectors
              ) -> PoseVectors:
    """The camera's true motion as the wheels measure it: off by SLIP (1 sigma)."""
    true = relative(before, after)
    slip = 1 + rng.normal(scale=SLIP, size=2)
    return PoseVectors(true.rvec * slip[1], true.tvec * slip[0])


def _largest_tags(world: np.ndarray, pose: PoseVectors, camera, count: int) -> np.ndarray:
    """Up to ``count`` corners (indices into ``world``, 4 per tag), tag by tag from the
    largest in the image among those whose four corners are in view: all four of each,
    and of the last one as many as are left, diagonal ones first (a device running a
    circuit of 6 points uses two tags, not one)."""
    inside, pix = _visible(world, pose, camera.K, camera.dist, camera.size)
    whole = [i for i in range(len(world) // 4) if inside[4 * i:4 * i + 4].all()]
    area = {i: cv2.contourArea(pix[4 * i:4 * i + 4].astype(np.float32)) for i in whole}
    chosen: list[int] = []
    for tag in sorted(whole, key=lambda i: -area[i]):
        chosen += [4 * tag + c for c in DIAGONAL_FIRST[:count - len(chosen)]]
        if len(chosen) == count:
            break
    return np.array(sorted(chosen), np.int64)


def _leg(step_m: float, turn_rad: float, most: int = 100_000) -> list[RobotPose]:
    """The robot's poses, a frame apart, driving by its controller on its true pose from
    START to TARGET, each move capped to a frame's."""
    robot, poses = START, [START]
    for _ in range(most):
        distance, turn, reached = control(robot, TARGET)
        if reached:
            break
        robot = robot.moved(float(np.clip(distance, -step_m, step_m)),
                            float(np.clip(turn, -turn_rad, turn_rad)))
        poses.append(robot)
    return poses


def make(name: str, rng: np.random.Generator, points: int, frames: int,
         **kw: float) -> Sequence:
    """A sequence by name (``SEQUENCES``)."""
    if name == "handheld":
        return handheld(rng, points, frames, **kw)
    if name == "turbo":
        return turbo(rng, points, frames, **kw)
    raise ValueError(f"--sequence: expected one of {SEQUENCES}, got {name!r}")
