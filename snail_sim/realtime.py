"""Turbo in real time: a robot whose pose advances with a clock, a camera that captures at
a fixed rate, and a controller that sets wheel speeds on every pose as it arrives.

``snail-demo turbo --realtime`` drives in this world. The robot never stops to think: it
keeps moving at its last command while a frame's pose is computed, so a pose describes
where the robot was when its frame was captured, and by the time it arrives the robot is
elsewhere. ``carried`` moves such a late pose over the odometry since its capture to where
the robot is now, and the controller (``Servo``) acts on that.

- ``Robot``: a log of commands (v m/s, w rad/s), each held until the next; between two
  commands the robot drives an exact arc. The true motion is the commanded one scaled by
  the wheels' slip, a factor that wanders slowly (AR(1), 3 % at 1 sigma, correlated over
  about a second, as tyres on one floor do), so odometry alone drifts. ``true_at(t)`` and
  ``odometry_at(t)`` answer for any instant since the start, past ones included: the
  camera's frames are rendered from the true pose at their capture time.
- ``FrameClock``: the camera's ticks, ``fps`` a second from ``t0``; a frame is the newest
  tick (what a camera driver hands out), never one older than the last frame taken.
- ``Servo``: Astolfi's polar controller in velocity form, cruising at the given speed,
  then a turn in place to the target's heading, then a hold: arrived once the estimate
  has stayed within the goal for ``SETTLE_FRAMES`` frames. A command holds until the next
  pose arrives, so its gains are sampled ones: told how long the last command held
  (``period``), the servo scales its gains to remove at most ``DAMP`` of an error per
  command. Without that, poses 0.4 s apart (a loaded core) made
  the final turn overshoot the goal's degree on every command and the robot never
  arrived.

Time is the clock's, in seconds (``time.monotonic`` unless a test passes its own).
"""

from __future__ import annotations

import bisect
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .turbo_world import GOAL_M, GOAL_RAD, RobotPose, wrap

SLIP = 0.03  # the wheels' slip, relative (1 sigma), as the step-by-step demo's
SLIP_TAU_S = 1.0  # how long the slip takes to change (its correlation time)
TURN_RATE = math.radians(45)  # rad/s at most, the turbo sequence's (snail_sim/sequences)
K_RHO, K_ALPHA, K_BETA = 2.0, 4.0, -1.5  # per second; Astolfi's strong stability:
# k_rho > 0 > k_beta, k_alpha + 5/3 k_beta - 2/pi k_rho > 0 (here 0.23)
K_TURN = 3.0  # per second, the final turn in place
CREEP = 0.02  # m/s at least while driving, and
CREEP_TURN = math.radians(2)  # rad/s at least while turning: no exponential tail
CLOSE_TURN = math.radians(10)  # rad/s at most within 3 cm, where the bearing is noise
STOP_M, STOP_RAD = 0.4 * GOAL_M, 0.4 * GOAL_RAD  # stop a phase well inside the goal: the
# estimate jitters by a few millimetres, and the robot must end within the goal in truth
SETTLE_FRAMES = 10  # frames held inside the goal before arriving (0.3-1 s)
DAMP = 0.5  # the share of an error one command may remove at most (module doc)

Clock = Callable[[], float]


def arc(pose: RobotPose, v: float, w: float, dt: float) -> RobotPose:
    """Where ``pose`` is after ``dt`` seconds at v (m/s, forward) and w (rad/s): an arc."""
    turn = w * dt
    if abs(turn) < 1e-9:
        return RobotPose(pose.x + v * dt * math.cos(pose.heading),
                         pose.y + v * dt * math.sin(pose.heading), pose.heading)
    radius = v / w
    heading = pose.heading + turn
    return RobotPose(pose.x + radius * (math.sin(heading) - math.sin(pose.heading)),
                     pose.y - radius * (math.cos(heading) - math.cos(pose.heading)),
                     wrap(heading))


def carried(estimate: RobotPose, since: RobotPose, now: RobotPose) -> RobotPose:
    """``estimate`` (of the robot when odometry read ``since``) moved by what odometry
    measured from ``since`` to ``now``, in the robot's own frame: where a late pose puts
    the robot now."""
    c, s = math.cos(since.heading), math.sin(since.heading)
    dx, dy = now.x - since.x, now.y - since.y
    forward, left = c * dx + s * dy, -s * dx + c * dy  # the move, in the robot's frame
    c, s = math.cos(estimate.heading), math.sin(estimate.heading)
    return RobotPose(estimate.x + c * forward - s * left, estimate.y + s * forward + c * left,
                     wrap(estimate.heading + now.heading - since.heading))


@dataclass(frozen=True)
class _Segment:
    """A command from ``start`` on, and where the robot (in truth, by odometry) was then."""

    start: float
    true: RobotPose
    odometry: RobotPose
    v: float
    w: float
    slip: tuple[float, float]  # true over commanded, forward and turning


class Robot:
    """Turbo on the clock (see the module docstring); odometry starts at the true pose."""

    def __init__(self, start: RobotPose, rng: np.random.Generator,
                 clock: Clock = time.monotonic, slip: float = SLIP) -> None:
        self.clock, self.rng, self.slip_sigma = clock, rng, slip
        self._slip = rng.normal(scale=slip, size=2)
        self._segments = [_Segment(clock(), start, start, 0.0, 0.0, (1.0, 1.0))]
        self._starts = [self._segments[0].start]

    @property
    def started(self) -> float:
        return self._starts[0]

    @property
    def command_now(self) -> tuple[float, float]:
        """The last command (v, w)."""
        last = self._segments[-1]
        return last.v, last.w

    def command(self, v: float, w: float) -> float:
        """Drive at v (m/s) and w (rad/s) from now on; returns now."""
        now = max(self.clock(), self._starts[-1])
        last = self._segments[-1]
        rho = math.exp(-(now - last.start) / SLIP_TAU_S)
        self._slip = rho * self._slip + math.sqrt(1 - rho ** 2) * self.rng.normal(
            scale=self.slip_sigma, size=2)
        segment = _Segment(now, self.true_at(now), self.odometry_at(now), v, w,
                           (1 + float(self._slip[0]), 1 + float(self._slip[1])))
        self._segments.append(segment)
        self._starts.append(now)
        return now

    def true_at(self, t: float) -> RobotPose:
        """The robot's true pose at ``t`` (not before the start)."""
        seg = self._segment(t)
        return arc(seg.true, seg.v * seg.slip[0], seg.w * seg.slip[1], t - seg.start)

    def odometry_at(self, t: float) -> RobotPose:
        """The pose odometry reads at ``t``: the commands integrated, no slip."""
        seg = self._segment(t)
        return arc(seg.odometry, seg.v, seg.w, t - seg.start)

    def _segment(self, t: float) -> _Segment:
        if t < self._starts[0]:
            raise ValueError(f"t = {t}: before the robot started ({self._starts[0]})")
        return self._segments[bisect.bisect_right(self._starts, t) - 1]


@dataclass(frozen=True)
class FrameClock:
    """The camera's ticks: tick k at ``t0 + k / fps``."""

    fps: float
    t0: float

    def at(self, tick: int) -> float:
        return self.t0 + tick / self.fps

    def newest(self, t: float) -> int:
        """The last tick at or before ``t``."""
        return math.floor((t - self.t0) * self.fps + 1e-9)


class Servo:
    """Wheel speeds from the estimate of where the robot is now (module docstring).

    Phases: ``drive`` (to the target's position, Astolfi, at most ``speed``), ``turn``
    (in place, to the target's heading), ``hold`` (stopped; arrived after SETTLE_FRAMES
    frames inside the goal; back to driving or turning if the estimate leaves it)."""

    def __init__(self, target: RobotPose, speed: float, turn_rate: float = TURN_RATE) -> None:
        if not speed > 0:
            raise ValueError(f"--speed: must be positive, got {speed}")
        self.target, self.speed, self.turn_rate = target, speed, turn_rate
        self.phase, self.held, self.arrived = "drive", 0, False

    def __call__(self, estimate: RobotPose, period: float = 0.0) -> tuple[float, float]:
        """(v, w) for ``estimate``, to hold about ``period`` seconds (0: unknown, the
        continuous gains); sets ``arrived`` once it has settled at the target."""
        # a command held ``period`` s may remove at most DAMP of an error per second...
        most = DAMP / period if period > 0 else math.inf
        dx, dy = self.target.x - estimate.x, self.target.y - estimate.y
        rho = math.hypot(dx, dy)
        heading_error = wrap(self.target.heading - estimate.heading)
        if self.phase != "drive" and rho > GOAL_M:
            self.phase, self.held = "drive", 0
        if self.phase == "hold" and abs(heading_error) > GOAL_RAD:
            self.phase, self.held = "turn", 0
        if self.phase == "drive" and rho < STOP_M:
            self.phase = "turn"
        if self.phase == "turn" and abs(heading_error) < STOP_RAD:
            self.phase = "hold"
        if self.phase == "hold":
            self.held += 1
            self.arrived = self.held >= SETTLE_FRAMES
            return 0.0, 0.0
        if self.phase == "turn":
            # the creep floor, too, removes no more than DAMP of the error
            floor = min(CREEP_TURN, most * abs(heading_error))
            rate = float(np.clip(min(K_TURN, most) * abs(heading_error), floor, self.turn_rate))
            return 0.0, math.copysign(rate, heading_error)
        alpha = wrap(math.atan2(dy, dx) - estimate.heading)
        beta = wrap(self.target.heading - math.atan2(dy, dx))
        backwards = abs(alpha) > math.pi / 2
        if backwards:  # the target is behind: back up to it (the rear is the front)
            alpha, beta = wrap(alpha + math.pi), wrap(beta + math.pi)
        turn_rate = self.turn_rate
        if rho < 3 * GOAL_M:  # close: creep straight at it, no more arcs
            beta, turn_rate = 0.0, min(turn_rate, CLOSE_TURN)
        # ...by Astolfi's gains scaled alike (its stability condition holds) and no more
        # than DAMP of the way
        scale = min(1.0, most / K_ALPHA)
        v = float(np.clip(scale * K_RHO * rho, min(CREEP, self.speed, most * rho), self.speed))
        w = float(np.clip(scale * (K_ALPHA * alpha + K_BETA * beta), -turn_rate, turn_rate))
        return (-v if backwards else v), w
