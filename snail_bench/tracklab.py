"""``snail-bench track --profile P``: the tracker across the network lab's links.

The daemons run in their namespaces (netlab/services.py), the links are shaped as the
profile says (FORMATS.md round 3) and measured, then ``snail-bench track`` runs unchanged
in the client's namespace against them. Each entry then gets ``link_bound_fps``: the rate
the links alone allow, 1 / max(a frame's garbled-table bytes over the measured server
rate, a frame's runs times the measured client round trip over the frames in flight).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

from snail_client.localize import Options

from .netlab.hosts import bdp_buffer, tune_tcp
from .netlab.namespaces import LINKS, Lab, LabError
from .netlab.profiles import profile_shapes
from .netlab.services import lab_services


def link_bound_fps(entry: dict, links: dict[str, dict]) -> float | None:
    """Frames per second the links alone allow for ``entry``'s frames."""
    table = entry.get("table_bytes_per_frame") or 0
    rate = links["garbler_evaluator"]["rate_mbit"]
    transfer = table * 8 / (rate * 1e6) if rate > 0 else 0.0
    trips = entry["runs_per_frame"] * links["client_evaluator"]["rtt_ms"] / 1000
    bound = max(transfer, trips / max(entry.get("in_flight") or 1, 1))
    return round(1 / bound, 3) if bound > 0 else None


def lab_report(profile: str, points: tuple[int, ...], frames: int, sequence: str,
               options: Options, feed_fps: float | None, odometry: bool,
               seed: int) -> dict:
    """``{"track": {...}}`` measured from the lab's client namespace, each entry with
    ``link_bound_fps``, and ``"links"``: every link's measured RTT and rate."""
    shapes = profile_shapes(profile)
    with tempfile.TemporaryDirectory(prefix="snail-track-lab-") as tmp, Lab() as lab:
        tune_tcp(lab, None, None, bdp_buffer(dict(shapes)) or None)
        with lab_services(lab, Path(tmp)) as services:
            lab.shape(shapes)
            links = {link: lab.measure(link, 1.0) for link in LINKS}
            cmd = [*lab.exec_prefix("client"), sys.executable, "-m", "snail_bench.cli", "-q",
                   "track", *_flags(points, frames, sequence, options, feed_fps, odometry,
                                    seed), *services.client_args(), "--json", "--per-frame"]
            proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        tail = proc.stderr.strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
        raise LabError(f"snail-bench track in the client's namespace failed: {tail[0]}")
    report = json.loads(proc.stdout)
    for entry in report["track"].values():
        entry["link_bound_fps"] = link_bound_fps(entry, links)
        entry["profile"] = profile
    report["links"] = links
    return report


def _flags(points: tuple[int, ...], frames: int, sequence: str, options: Options,
           feed_fps: float | None, odometry: bool, seed: int) -> list[str]:
    """The same measurement's flags for the run inside the lab."""
    flags = [*(arg for n in points for arg in ("--points", str(n))), "--frames", str(frames),
             "--sequence", sequence, "--runs-per-frame", str(options.runs_per_frame),
             "--algorithm", options.algorithm, "--step", options.step,
             "--motion-model", options.motion_model,
             "--scheme", options.scheme, "--seed", str(seed)]
    for flag, value in (("--in-flight", options.in_flight), ("--rate", options.rate),
                        ("--feed-fps", feed_fps)):
        if value is not None:
            flags += [flag, str(value)]
    return flags + (["--odometry"] if odometry else [])
