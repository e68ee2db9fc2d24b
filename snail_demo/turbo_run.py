"""``snail-demo turbo``: run Turbo (step by step, or in real time with ``--realtime``) and
write its log, video, animation and trajectory plot."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from snail_client.api import Localizer
from snail_client.progress import bar

from .draw import frame, realtime_plot, top_down
from .render import Look
from .turbo import START, TARGET, RobotPose, drive, robot_camera, room, summary
from .turbo_realtime import RealtimeRun, drive_realtime, summary_realtime

FPS = 4
MAX_TAGS = 4  # the 4 largest tags in view, padded to 16 points: one circuit for every frame


def run_turbo(out: Path, backend: str, link_delay_ms: float, min_invocations: int,
              max_steps: int, seed: int, quiet: bool = False, verbose: bool = False) -> dict:
    """Drive from START to TARGET; returns the final summary (also in turbo.json)."""
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    look = Look(blur_px=0.8, noise=3.0, background=120)
    video = None
    with Localizer(camera=robot_camera(), tag_map=room(), backend=backend,
                   min_invocations=min_invocations, max_tags=MAX_TAGS,
                   pad_points=4 * MAX_TAGS) as loc, bar(
            max_steps, "control steps", quiet, unit="step") as progress:
        if link_delay_ms:
            delay = 2 * link_delay_ms / 1000
            loc.backend.on_invocation = lambda: time.sleep(delay)

        def on_step(run, image, pose):
            nonlocal video
            picture = frame(run, image, pose, TARGET, loc.tag_map, loc.camera)
            if video is None:
                height, width = picture.shape[:2]
                video = cv2.VideoWriter(str(out / "turbo.mp4"),
                                        cv2.VideoWriter_fourcc(*"mp4v"), FPS, (width, height))
            video.write(picture)
            if len(run.steps) == 1:
                cv2.imwrite(str(out / "first_frame.png"), picture)
            cv2.imwrite(str(out / "last_frame.png"), picture)
            progress.update(1)
            if verbose:
                progress.write(f"step {len(run.steps)}: {json.dumps(run.steps[-1])}",
                               file=sys.stderr)

        try:
            run = drive(loc, START, TARGET, max_steps, rng, look, on_step)
        finally:
            if video is not None:
                video.release()
    cv2.imwrite(str(out / "trajectory.png"), top_down(run, TARGET, loc.tag_map, 720))
    final = summary(run, TARGET)
    final.update(backend=backend, min_invocations=min_invocations,
                 link_delay_ms=link_delay_ms)
    (out / "turbo.json").write_text(json.dumps({"steps": run.steps, "final": final},
                                               indent=1) + "\n")
    return final


VIDEO_FPS = 10  # frames kept a second of the drive: turbo.mp4 plays in real time
GIF_FPS = 5  # turbo.gif: every other one (a GIF of camera noise is ~50 kB a frame)
GIF_WIDTH = 720  # px: the side-by-side frame (1120 x 480) scaled for a page


def run_turbo_realtime(out: Path, backend: str, speed: float, camera_fps: float,
                       max_seconds: float, min_invocations: int, runs_per_frame: int,
                       seed: int, quiet: bool = False, verbose: bool = False,
                       start: RobotPose = START) -> dict:
    """Drive from ``start`` to TARGET in real time (turbo_realtime.py); returns the summary
    (also in turbo.json) and writes the video, the animation and the trajectory plot."""
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    look = Look(blur_px=0.8, noise=3.0, background=120)
    with Localizer(camera=robot_camera(), tag_map=room(), backend=backend,
                   min_invocations=min_invocations, max_tags=MAX_TAGS,
                   pad_points=4 * MAX_TAGS, runs_per_frame=runs_per_frame,
                   in_flight=1) as loc:
        if not quiet:
            print(f"driving to the target at {speed:g} m/s ...", file=sys.stderr)
        run = drive_realtime(loc, start, TARGET, speed, camera_fps, max_seconds, rng, look,
                             picture_every_s=1 / VIDEO_FPS)
        tagmap, camera = loc.tag_map, loc.camera
    final = summary_realtime(run, TARGET, speed, camera_fps)
    final.update(backend=backend, min_invocations=min_invocations,
                 runs_per_frame=runs_per_frame, realtime=True)
    if verbose:
        for k, step in enumerate(run.steps):
            print(f"frame {k}: {json.dumps(step)}", file=sys.stderr)
    pictures = [frame(RealtimeRun(run.steps[:p.index + 1], run.true_path[:p.index + 1],
                                  run.estimates[:p.index + 1]),
                      p.image, p.pose, TARGET, tagmap, camera,
                      realtime_lines(run.steps[p.index], p.index))
                for p in run.pictures]
    timeline = on_the_clock(pictures, [p.slot for p in run.pictures])
    _write_video(out / "turbo.mp4", timeline, VIDEO_FPS)
    every = round(VIDEO_FPS / GIF_FPS)
    write_gif(out / "turbo.gif", timeline[::-every][::-1], GIF_FPS, GIF_WIDTH)
    cv2.imwrite(str(out / "first_frame.png"), pictures[0])
    cv2.imwrite(str(out / "last_frame.png"), pictures[-1])
    cv2.imwrite(str(out / "trajectory.png"), realtime_plot(run, TARGET, tagmap, 720))
    (out / "turbo.json").write_text(json.dumps({"steps": run.steps, "final": final},
                                               indent=1) + "\n")
    return final


def realtime_lines(step: dict, index: int) -> list[str]:
    """A frame's numbers on the animation: clock, speed, what the frame cost."""
    return [f"t {step['t']:.1f} s  frame {index}  {step['status']}, {step['runs']} secure "
            f"run{'s' if step['runs'] != 1 else ''}  {step['phase']}",
            f"{100 * step['command']['speed_mps']:.0f} cm/s  pose "
            f"{1000 * step['latency_s']:.0f} ms after capture  error now "
            f"{1000 * step['position_error_now_m']:.1f} mm"]


def on_the_clock(pictures: list[np.ndarray], slots: list[int]) -> list[np.ndarray]:
    """One picture per slot of the wall clock (drive_realtime's) from the first to the
    last: each shows the newest pose that had arrived by then, so the video plays in real
    time even when poses come slower than its rate (a loaded machine) or at a rate that
    does not divide it."""
    repeats = np.append(np.diff(slots), 1).clip(min=0)
    return [picture for picture, n in zip(pictures, repeats) for _ in range(n)]


def _write_video(path: Path, pictures: list[np.ndarray], fps: float) -> None:
    height, width = pictures[0].shape[:2]
    video = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (width, height))
    try:
        for picture in pictures:
            video.write(picture)
    finally:
        video.release()


def write_gif(path: Path, pictures: list[np.ndarray], fps: float, width: int) -> bool:
    """An animated GIF of ``pictures`` (BGR) at ``fps``, ``width`` px wide, with OpenCV's
    encoder (4.12 and later: no other dependency); False, and no file, without one."""
    if not hasattr(cv2, "imwriteanimation"):
        print(f"warning: {path.name} not written: OpenCV {cv2.__version__} has no GIF "
              "encoder (4.12 or later has)", file=sys.stderr)
        return False
    animation = cv2.Animation()
    scale = width / pictures[0].shape[1]
    animation.frames = [cv2.resize(p, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
                        for p in pictures]
    animation.durations = [round(1000 / fps)] * len(pictures)
    try:
        return bool(cv2.imwriteanimation(str(path), animation))
    except cv2.error as exc:
        print(f"warning: {path.name} not written: {exc}", file=sys.stderr)
        return False
