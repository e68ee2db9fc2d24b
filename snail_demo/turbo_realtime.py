"""Turbo in real time (``snail-demo turbo --realtime``): the robot drives continuously while
its poses are computed privately, one secure run per camera frame.

The loop, on the world of ``snail_sim.realtime``:

1. the camera hands out its newest frame: the room rendered from the robot's true pose at
   that tick (the robot has moved on while it renders, as it does while a real camera
   reads out);
2. ``Localizer.track`` localizes it on the fixed schedule (a padded first frame, then
   ``runs_per_frame`` secure runs a frame, one Gauss-Newton/LM step each), predicted from
   the last pose moved by Turbo's odometry between the two frames' capture times (the
   commanded motion: the wheels' slip is what the step corrects);
3. the pose describes the robot at capture; ``carried`` moves it over the odometry since
   to where the robot is now, and the controller sets the wheel speeds from that. An
   answer that fails its checks (or a frame without a tag) changes nothing: the last
   trusted pose, carried by odometry, steers.

The tracker pulls the next frame only once this one's pose has been acted on (one frame in
flight: the loop is closed). The robot stops for good once the controller has held it at
the target for a few frames; the summary measures the true pose against the target.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from snail_client.api import Localizer, Pose
from snail_common.loc.schedule import relative
from snail_sim.realtime import Clock, FrameClock, Robot, Servo, carried
from snail_sim.turbo_world import GOAL_M, GOAL_RAD, RobotPose, wrap

from .render import Look, render
from .turbo import _pose_json


@dataclass(frozen=True)
class Capture:
    """One camera frame: its tick, capture time, and the robot then (truth, odometry)."""

    tick: int
    t: float
    true: RobotPose
    odometry: RobotPose
    render_s: float  # the simulator's rendering, wall and CPU: not the device's work
    render_cpu_s: float


@dataclass(frozen=True)
class Picture:
    """A frame kept for the animation: its index, the wall-clock slot its pose arrived in,
    the camera image and the pose."""

    index: int
    slot: int
    image: np.ndarray
    pose: Pose


@dataclass
class RealtimeRun:
    """What happened, frame by frame (turbo.json's steps) and for drawing: the true pose
    and the estimate at each frame's capture, and the frames kept for the animation."""

    steps: list[dict] = field(default_factory=list)
    true_path: list[RobotPose] = field(default_factory=list)
    estimates: list[RobotPose] = field(default_factory=list)
    pictures: list[Picture] = field(default_factory=list)
    end: RobotPose | None = None  # the true pose once the robot stopped
    wall_s: float = 0.0


class _Camera:
    """Frames for ``Localizer.track``: the newest tick's image, waiting for the next tick
    when the newest was taken already; ``captures[i]`` says when frame i was taken."""

    def __init__(self, robot: Robot, localizer: Localizer, fps: float, look: Look,
                 rng: np.random.Generator) -> None:
        self.robot, self.loc, self.look, self.rng = robot, localizer, look, rng
        self.ticks = FrameClock(fps, robot.clock())
        self.captures: list[Capture] = []
        self.image: np.ndarray | None = None  # the last frame's
        self.stop = False

    def frames(self):
        """The images, until ``stop`` is set (checked before each capture)."""
        clock = self.robot.clock
        while not self.stop:
            tick = self.ticks.newest(clock())
            if self.captures and tick <= self.captures[-1].tick:
                tick = self.captures[-1].tick + 1
                time.sleep(max(0.0, self.ticks.at(tick) - clock()))
            t = self.ticks.at(tick)
            true = self.robot.true_at(t)
            began, cpu = time.perf_counter(), time.process_time()
            self.image = render(self.loc.tag_map, self.loc.camera, true.camera(), self.look,
                                self.rng)
            self.captures.append(Capture(tick, t, true, self.robot.odometry_at(t),
                                         time.perf_counter() - began,
                                         time.process_time() - cpu))
            yield self.image

    def motion(self, index: int):
        """Frame ``index``'s odometry: the camera's commanded motion since the frame before."""
        if index == 0:
            return None
        before, after = self.captures[index - 1], self.captures[index]
        return relative(before.odometry.camera(), after.odometry.camera())


def drive_realtime(localizer: Localizer, start: RobotPose, target: RobotPose, speed: float,
                   camera_fps: float, max_seconds: float, rng: np.random.Generator,
                   look: Look, clock: Clock = time.monotonic,
                   picture_every_s: float = 0.1) -> RealtimeRun:
    """Drive from ``start`` to ``target`` at ``speed`` m/s on the wall clock (module
    docstring); keeps for the animation the first frame whose pose arrives in each
    ``picture_every_s`` slot of the wall clock, with its slot (a slot no pose arrived in
    has none)."""
    run = RealtimeRun()
    robot = Robot(start, rng, clock)
    camera = _Camera(robot, localizer, camera_fps, look, rng)
    servo = Servo(target, speed)
    anchor: tuple[RobotPose, RobotPose] | None = None  # (trusted estimate, odometry then)
    began, last_slot = robot.started, -1
    commanded: float | None = None  # when the last command was given
    cpu = time.process_time()
    for index, pose in enumerate(localizer.track(camera.frames(), motion=camera.motion)):
        now = clock()
        cap = camera.captures[index]
        if pose.trusted:
            anchor = (RobotPose.from_camera(pose.rvec, pose.tvec), cap.odometry)
        elif anchor is None:
            raise RuntimeError(f"the first frame gave no pose ({pose.status}): no tag in "
                               "view at the start?")
        at_capture = carried(anchor[0], anchor[1], cap.odometry)
        estimate = carried(anchor[0], anchor[1], robot.odometry_at(now))
        period = now - commanded if commanded is not None else 0.0  # it held that long
        v, w = servo(estimate, period)
        commanded = now
        true_now = robot.true_at(robot.command(v, w))
        if index and now - began > max_seconds and not servo.arrived:
            robot.command(0.0, 0.0)  # out of time: stop where it is
            camera.stop = True
        cpu_now = time.process_time()
        record = pose.record
        traffic = int(sum(record.get("traffic", {}).values()))
        run.steps.append({
            "t": round(now - began, 4), "tick": cap.tick, "t_capture": round(cap.t - began, 4),
            "latency_s": round(now - cap.t, 5), "render_s": round(cap.render_s, 5),
            "true": _pose_json(cap.true.camera()), "estimate": _pose_json(at_capture.camera()),
            "robot_true": [cap.true.x, cap.true.y, math.degrees(cap.true.heading)],
            "robot_estimate": [at_capture.x, at_capture.y, math.degrees(at_capture.heading)],
            "robot_true_now": [true_now.x, true_now.y, math.degrees(true_now.heading)],
            "robot_estimate_now": [estimate.x, estimate.y, math.degrees(estimate.heading)],
            "status": pose.status, "track_status": record.get("track_status"),
            "revealed": bool(record.get("revealed")), "tags": list(pose.tag_ids),
            "runs": int(record.get("runs", 0)), "iterations": int(record.get("iterations", 0)),
            "invocations": int(record.get("invocations", 0)),
            "seconds": float(record.get("latency_s", 0.0)), "bytes": traffic,
            "client_cpu_s": round(cpu_now - cpu - cap.render_cpu_s, 5),
            "position_error_m": math.hypot(at_capture.x - cap.true.x, at_capture.y - cap.true.y),
            "position_error_now_m": math.hypot(estimate.x - true_now.x, estimate.y - true_now.y),
            "command": {"speed_mps": v, "turn_deg_s": math.degrees(w), "period_s": period},
            "phase": servo.phase,
        })
        cpu = cpu_now
        run.true_path.append(cap.true)
        run.estimates.append(at_capture)
        slot = math.floor((now - began) / picture_every_s)
        if slot > last_slot or servo.arrived or camera.stop:
            run.pictures.append(Picture(index, slot, camera.image, pose))
            last_slot = slot
        if servo.arrived:
            camera.stop = True
    run.wall_s = clock() - began
    run.end = robot.true_at(clock())
    return run


def summary_realtime(run: RealtimeRun, target: RobotPose, speed: float,
                     camera_fps: float) -> dict:
    """The final errors against the target from the true pose once stopped, and how fast
    the private poses came (FORMATS.md round 4: ``speed_mps``, ``fps``, ``latency_s``)."""
    end = run.end if run.end is not None else run.true_path[-1]
    position = math.hypot(end.x - target.x, end.y - target.y)
    rotation = abs(math.degrees(wrap(end.heading - target.heading)))
    first, later = run.steps[0], run.steps[1:]
    latencies = [s["latency_s"] for s in later]
    p50, p95 = np.percentile(latencies, [50, 95]) if latencies else (math.nan, math.nan)
    driving = later[-1]["t"] - first["t"] if later else 0.0
    path = sum(math.hypot(b.x - a.x, b.y - a.y)
               for a, b in zip(run.true_path, run.true_path[1:]))
    return {
        "position_error_m": position, "rotation_error_deg": rotation,
        "reached": position <= GOAL_M and rotation <= math.degrees(GOAL_RAD),
        "steps": len(run.steps), "speed_mps": speed,
        "fps": round(len(later) / driving, 3) if driving else None,
        "latency_s": {"p50": round(float(p50), 5), "p95": round(float(p95), 5),
                      "max": round(max(latencies), 5) if latencies else None},
        "first_frame_s": first["latency_s"], "camera_fps": camera_fps,
        "drive_s": round(driving, 3), "wall_s": round(run.wall_s, 3),
        "path_m": round(path, 4),
        "mean_speed_mps": round(path / driving, 4) if driving else None,
        "max_position_error_now_m": max(s["position_error_now_m"] for s in run.steps),
        "runs_first_frame": first["runs"], "runs_after_first": sorted({s["runs"] for s in later}),
        "secure_runs": sum(s["runs"] for s in run.steps),
        "untrusted": sum(s["status"] not in ("converged", "tracked") for s in run.steps),
        "revealed": sum(s["revealed"] for s in run.steps),
        "median_render_s": float(np.median([s["render_s"] for s in run.steps])),
        "median_client_cpu_s": float(np.median([s["client_cpu_s"] for s in run.steps])),
        "total_bytes": int(sum(s["bytes"] for s in run.steps)),
    }
