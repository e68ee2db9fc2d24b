"""Pictures of a Turbo run, drawn with OpenCV (no plotting dependency): the camera view
with the detected tags and the estimated pose, and a top-down map of the room with the
true and estimated paths."""

from __future__ import annotations

import math

import cv2
import numpy as np

from snail_client.api import Pose
from snail_client.inputs.apriltag import detect
from snail_client.inputs.camera import Camera
from snail_client.inputs.tagmap import TagMap

from .turbo import RobotPose, Run
from .turbo_realtime import RealtimeRun

MAP_PX = 480
BOUNDS = (-0.2, 2.4, -1.2, 1.2)  # x0, x1, y0, y1 of the room in metres
GREEN, RED, BLUE, GREY, BLACK = (60, 170, 60), (40, 40, 220), (200, 120, 30), (150,) * 3, (0,) * 3


def _to_px(x: float, y: float, size: int) -> tuple[int, int]:
    """World (x forward, y left) to map pixels (x up the image, y to the left)."""
    x0, x1, y0, y1 = BOUNDS
    scale = size / max(x1 - x0, y1 - y0)
    return round((y1 - y) * scale), round((x1 - x) * scale)


def camera_view(image: np.ndarray, pose: Pose | None, tagmap: TagMap,
                camera: Camera) -> np.ndarray:
    """The image with each detected tag outlined (green) and the map's tags projected with
    the estimated pose (red corners): where they sit on the green, the pose is right."""
    view = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    found = detect(image)
    for corners in found.corners:
        cv2.polylines(view, [np.round(corners).astype(np.int32)], True, GREEN, 2)
    if pose is not None:
        for tag in tagmap.tags.values():
            pts, _ = cv2.projectPoints(tag.corners_world(), pose.rvec, pose.tvec, camera.K,
                                       camera.dist)
            R, _ = cv2.Rodrigues(pose.rvec)
            if (tag.corners_world() @ R.T + pose.tvec)[:, 2].min() <= 0:
                continue
            for p in pts.reshape(-1, 2):
                if np.all(np.abs(p) < 4000):
                    cv2.circle(view, (int(p[0]), int(p[1])), 3, RED, -1)
    return view


def top_down(run: Run | RealtimeRun, target: RobotPose, tagmap: TagMap,
             size: int = MAP_PX) -> np.ndarray:
    """The room from above: tags (black), target (grey), true path (blue), estimates
    (red; small dots under the path when there is one a camera frame), the robot now
    (blue triangle)."""
    canvas = np.full((size, size, 3), 255, np.uint8)
    for tag in tagmap.tags.values():
        ends = tag.corners_world()[[0, 1]]
        cv2.line(canvas, _to_px(*ends[0][:2], size), _to_px(*ends[1][:2], size), BLACK, 3)
    _robot(canvas, target, GREY, size)
    true = [_to_px(p.x, p.y, size) for p in run.true_path]
    dense = isinstance(run, RealtimeRun)
    if len(true) > 1 and not dense:
        cv2.polylines(canvas, [np.array(true, np.int32)], False, BLUE, 2)
    for p in run.estimates:
        cv2.circle(canvas, _to_px(p.x, p.y, size), 2 if dense else 3, RED, -1)
    if len(true) > 1 and dense:
        cv2.polylines(canvas, [np.array(true, np.int32)], False, BLUE, 1, cv2.LINE_AA)
    if run.true_path:
        _robot(canvas, run.true_path[-1], BLUE, size)
    for k, (text, colour) in enumerate([("true path", BLUE), ("private estimates", RED),
                                        ("target", GREY), ("tags", BLACK)]):
        cv2.putText(canvas, text, (10, size - 70 + 18 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    colour, 1, cv2.LINE_AA)
    return canvas


def _robot(canvas: np.ndarray, pose: RobotPose, colour: tuple, size: int) -> None:
    r = 0.06
    tip = (pose.x + r * math.cos(pose.heading), pose.y + r * math.sin(pose.heading))
    left = (pose.x + r * math.cos(pose.heading + 2.5), pose.y + r * math.sin(pose.heading + 2.5))
    right = (pose.x + r * math.cos(pose.heading - 2.5), pose.y + r * math.sin(pose.heading - 2.5))
    pts = np.array([_to_px(*p, size) for p in (tip, left, right)], np.int32)
    cv2.fillPoly(canvas, [pts], colour)


def step_lines(run: Run) -> list[str]:
    """A control step's numbers, for the step-by-step demo's video."""
    step = run.steps[-1]
    return [f"step {len(run.steps)}  {step['status']}  {step['iterations']} iterations, "
            f"{step['invocations']} secure runs",
            f"{step['seconds']:.2f} s, {step['bytes'] / 1e6:.1f} MB, client CPU "
            f"{step['client_cpu_s']:.2f} s, error {100 * step['position_error_m']:.1f} cm"]


def frame(run: Run | RealtimeRun, image: np.ndarray, pose: Pose | None, target: RobotPose,
          tagmap: TagMap, camera: Camera, lines: list[str] | None = None) -> np.ndarray:
    """One video frame: camera view and map side by side, with ``lines`` of numbers (by
    default the last step's)."""
    left = camera_view(image, pose, tagmap, camera)
    for k, text in enumerate(step_lines(run) if lines is None else lines):
        cv2.putText(left, text, (8, 20 + 20 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 200, 255),
                    1, cv2.LINE_AA)
    return np.hstack([left, top_down(run, target, tagmap, left.shape[0])])


INSET_M = 0.05  # the inset's half-width around the target, metres


def realtime_plot(run: RealtimeRun, target: RobotPose, tagmap: TagMap,
                  size: int = 720) -> np.ndarray:
    """A real-time drive's trajectory.png: the room from above with the last centimetres
    magnified around the target (the goal's 1 cm circle), over the drive's timeline."""
    canvas = top_down(run, target, tagmap, size)
    inset = _inset(run, target, size // 3)
    x0, y0 = 10, size - 90 - inset.shape[0]
    canvas[y0:y0 + inset.shape[0], x0:x0 + inset.shape[1]] = inset
    return np.vstack([canvas, timeline(run, size)])


def _inset(run: RealtimeRun, target: RobotPose, px: int) -> np.ndarray:
    """The target's surroundings, INSET_M each way: the goal circle (GOAL_M), the true
    path and the estimates near it, and where the robot stopped."""
    from snail_sim.turbo_world import GOAL_M

    canvas = np.full((px, px, 3), 255, np.uint8)
    scale = px / (2 * INSET_M)

    def at(x: float, y: float) -> tuple[int, int]:  # as _to_px: x up, y to the left
        return (round(px / 2 + (target.y - y) * scale), round(px / 2 + (target.x - x) * scale))

    cv2.circle(canvas, at(target.x, target.y), round(GOAL_M * scale), GREY, 1, cv2.LINE_AA)
    near = [p for p in run.estimates if abs(p.x - target.x) < INSET_M
            and abs(p.y - target.y) < INSET_M]
    for p in near:
        cv2.circle(canvas, at(p.x, p.y), 2, RED, -1)
    true = [at(p.x, p.y) for p in run.true_path]
    if len(true) > 1:
        cv2.polylines(canvas, [np.array(true, np.int32)], False, BLUE, 1, cv2.LINE_AA)
    end = run.end if run.end is not None else (run.true_path[-1] if run.true_path else None)
    if end is not None:
        cv2.drawMarker(canvas, at(end.x, end.y), BLUE, cv2.MARKER_CROSS, 12, 2)
    cv2.drawMarker(canvas, at(target.x, target.y), GREY, cv2.MARKER_TILTED_CROSS, 8, 1)
    cv2.rectangle(canvas, (0, 0), (px - 1, px - 1), BLACK, 1)
    cv2.putText(canvas, f"target +/-{100 * INSET_M:.0f} cm, circle {100 * GOAL_M:.0f} cm",
                (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.4, BLACK, 1, cv2.LINE_AA)
    return canvas


def timeline(run: RealtimeRun, width: int, panel: int = 100) -> np.ndarray:
    """Along the drive's clock, a panel each: the commanded speed (cm/s), each pose's
    latency from its frame's capture (ms, the padded first frame's off the scale) and how
    far the estimate the controller steered on was from the truth then (mm)."""
    steps = run.steps
    series = [("commanded speed, cm/s", [100 * s["command"]["speed_mps"] for s in steps]),
              ("pose latency from capture, ms", [1000 * s["latency_s"] for s in steps]),
              ("steering estimate's error, mm", [1000 * s["position_error_now_m"]
                                                 for s in steps])]
    times = [s["t"] for s in steps]
    span = max(times[-1], 1e-3) if times else 1.0
    left, right = 50, 12
    out = []
    for k, (name, values) in enumerate(series):
        canvas = np.full((panel, width, 3), 255, np.uint8)
        later = values[1:] or values
        top = _nice(max(np.percentile(later, 99) * 1.15, 1e-6)) if later else 1.0
        inner = panel - 28

        def at(t: float, v: float, top=top, inner=inner) -> tuple[int, int]:
            return (round(left + t / span * (width - left - right)),
                    round(8 + inner * (1 - min(max(v / top, 0.0), 1.0))))

        cv2.line(canvas, (left, 8), (left, 8 + inner), GREY, 1)
        cv2.line(canvas, (left, 8 + inner), (width - right, 8 + inner), GREY, 1)
        if len(values) > 1:
            cv2.polylines(canvas, [np.array([at(t, v) for t, v in zip(times, values)],
                                            np.int32)], False, (RED, BLUE, GREEN)[k], 1,
                          cv2.LINE_AA)
        cv2.putText(canvas, f"{top:g}", (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.4, BLACK, 1,
                    cv2.LINE_AA)
        cv2.putText(canvas, "0", (30, 8 + inner + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, BLACK,
                    1, cv2.LINE_AA)
        cv2.putText(canvas, name, (left + 8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.45, BLACK, 1,
                    cv2.LINE_AA)
        for second in range(int(span) + 1):
            x = at(second, 0)[0]
            cv2.line(canvas, (x, 8 + inner), (x, 8 + inner + 4), GREY, 1)
            if k == len(series) - 1:
                cv2.putText(canvas, f"{second} s" if second else "0", (x - 6, panel - 4),
                            cv2.FONT_HERSHEY_SIMPLEX, 0.38, BLACK, 1, cv2.LINE_AA)
        out.append(canvas)
    return np.vstack(out)


def _nice(value: float) -> float:
    """The next of 1, 2, 5 times a power of ten at or above ``value``."""
    power = 10 ** math.floor(math.log10(value))
    return next(m * power for m in (1, 2, 5, 10) if m * power >= value)
