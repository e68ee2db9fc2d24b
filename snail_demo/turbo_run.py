"""``snail-demo turbo``: run Turbo and write its log, video and trajectory plot."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from snail_client.api import Localizer
from snail_client.progress import bar

from .draw import frame, top_down
from .render import Look
from .turbo import START, TARGET, drive, robot_camera, room, summary

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
