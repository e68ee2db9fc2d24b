"""``snail-bench track``: the flags, their checks and what a person reads; the measuring
is ``track.py`` (and ``tracklab.py`` under ``--profile``)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import click

from snail_common.loc.schedule import MOTION_MODELS
from snail_common.net.linkrates import AUTO, CLIENT_SCHEMES
from snail_sim.sequences import SEQUENCES

PROFILES = ("lan", "paper", "region", "continent")


@click.command("track")
@click.option("--points", type=click.IntRange(4, 4096), multiple=True, metavar="N",
              help="Points a frame (repeat for several; default 6). Turbo's frames take "
                   "up to N corners of its largest tags in view (2-4 tags: 16 is the "
                   "demo's circuit; 6 takes a tag and the diagonal of the next), padded "
                   "to N.")
@click.option("--frames", type=click.IntRange(2, 1_000_000), default=600, show_default=True,
              help="Frames of the sequence (30 frames/s of camera time).")
@click.option("--sequence", type=click.Choice(SEQUENCES), default="handheld",
              show_default=True,
              help="handheld: a camera carried at 0.5 m/s (half a degree a frame, hand "
                   "shake, 0.5 px noise drifting as tracked features' does) through a room "
                   "of points; turbo: Turbo's drive at 0.3 m/s among the room's tags (its "
                   "distorted wide-angle camera).")
@click.option("--runs-per-frame", type=click.IntRange(1, 100), default=1, show_default=True,
              help="Secure runs every frame after the first (each one GN or LM step).")
@click.option("--in-flight", type=click.IntRange(1, 16), metavar="D",
              help="Frames whose runs overlap (default: from the first frame's runs).")
@click.option("--feed-fps", type=click.FloatRange(0, min_open=True), metavar="F",
              help="Feed the frames as a camera at F frames/s (from when the first "
                   "localization is back; a tracker behind takes the newest frame, the "
                   "others count as dropped). Default: as fast as the tracker takes them.")
@click.option("--rate", type=click.FloatRange(0, min_open=True), metavar="R",
              help="Secure runs at R per second whatever the frames (the tracker's --rate).")
@click.option("--profile", type=click.Choice(PROFILES),
              help="The network lab's links (root only: three namespaces on this host); "
                   "adds link_bound_fps, the rate the links alone allow.")
@click.option("--map-points", type=click.IntRange(4, 1_000_000), metavar="M",
              help="The map-owner setting: the hand-held room's M points held by a "
                   "snail-mapd on loopback, each frame's points selected from them by OT.")
@click.option("--relay", is_flag=True,
              help="With --map-points: the device reaches the map owner only through the "
                   "evaluator (the client's --relay), the entry's relay true.")
@click.option("--algorithm", type=click.Choice(["lm", "gn"]), default="lm",
              show_default=True, help="The padded first frame's algorithm.")
@click.option("--step", type=click.Choice(["gn", "lm"]), default="gn", show_default=True,
              help="The step each later run makes (the tracker's --step).")
@click.option("--motion-model", type=click.Choice(MOTION_MODELS), default="auto",
              show_default=True, help="The tracker's prediction.")
@click.option("--odometry", is_flag=True,
              help="Turbo only: pass its wheel odometry (3 % slip) as the tracker's motion.")
@click.option("--backend", type=click.Choice(["garbled", "cleartext", "float64"]),
              default="garbled", show_default=True,
              help="garbled: embedded daemons on loopback (the figures); cleartext: the same "
                   "circuits in the clear (the same poses, bit for bit).")
@click.option("--scheme", type=click.Choice(list(CLIENT_SCHEMES)), default=AUTO,
              show_default=True, help="Garbling scheme of every session.")
@click.option("--seed", type=int, default=1, show_default=True, help="Sequence seed.")
@click.option("--figure", type=click.Path(dir_okay=False), metavar="PNG",
              help="Also draw per-frame latency and RMS ratio along the sequence "
                   "(matplotlib: the bench extra).")
@click.option("--garbler", metavar="HOST:PORT", help="Running servers (with --evaluator and "
              "--tls-dir) instead of embedded ones.")
@click.option("--evaluator", metavar="HOST:PORT")
@click.option("--tls-dir", type=click.Path(exists=True, file_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (FORMATS.md).")
@click.option("--per-frame", is_flag=True, hidden=True,
              help="Keep each entry's per-frame rows in the JSON (what --figure draws).")
def track(points: tuple[int, ...], frames: int, sequence: str, runs_per_frame: int,
          in_flight: int | None, feed_fps: float | None, rate: float | None,
          profile: str | None, map_points: int | None, relay: bool, algorithm: str, step: str,
          motion_model: str, odometry: bool, backend: str, scheme: str, seed: int,
          figure: str | None, garbler: str | None, evaluator: str | None, tls_dir: str | None,
          as_json: bool, per_frame: bool) -> None:
    """Follow a made-up camera privately at its rate: frames/s, latency (frame handed in
    to pose out) and every frame's pose against OpenCV's converged solvePnP.

    2026-12-04, a 2-core machine, both servers on it, loopback, 600 frames, one run a
    frame: n = 6 82-85 frames/s, fed at 30 frames/s p95 latency 16-17 ms; n = 16 37-41
    frames/s; 99.7-99.8 % of frames within 1 % of OpenCV's RMS (docs/tracking.md has
    every row)."""
    from snail_client.links import ServiceError
    from snail_client.localize import Options
    from snail_client.relay import EVALUATOR

    from .netlab.namespaces import LabError, LabUnavailable

    if map_points and sequence != "handheld":
        raise click.UsageError("--map-points: with --sequence handheld (the map is its room)")
    if relay and not map_points:
        raise click.UsageError("--relay: with --map-points (it is the way to the map owner)")
    if odometry and sequence != "turbo":
        raise click.UsageError("--odometry: Turbo's (--sequence turbo)")
    if profile and (garbler or backend != "garbled"):
        raise click.UsageError("--profile runs its own daemons in the lab, garbled")
    try:
        options = Options(backend=backend, algorithm=algorithm, step=step,
                          runs_per_frame=runs_per_frame, in_flight=in_flight, rate=rate,
                          motion_model=motion_model,
                          scheme=scheme, garbler=garbler, evaluator=evaluator, tls_dir=tls_dir,
                          relay=EVALUATOR if relay else None,
                          **({"solve": "circuit"} if map_points else {}))
    except ValueError as e:
        raise click.UsageError(str(e)) from None
    points = points or (6,)
    try:
        if profile:
            from .tracklab import lab_report

            report = lab_report(profile, points, frames, sequence, options, feed_fps,
                                odometry, seed)
        else:
            from .track import track_report

            report = track_report(points, frames, sequence, options, feed_fps, map_points,
                                  odometry, seed)
    except (ServiceError, LabError) as e:
        click.echo(f"snail-bench: {e}", err=True)
        sys.exit(1)
    except LabUnavailable as e:  # not root, no network namespaces
        click.echo(f"snail-bench: --profile needs the network lab: {e}", err=True)
        sys.exit(2)
    if figure:
        from .track_plot import draw

        draw(report, Path(figure))
    for entry in report["track"].values():
        if not per_frame:
            entry.pop("per_frame", None)
    if as_json:
        click.echo(json.dumps(report))
        return
    for name, e in report["track"].items():
        click.echo(_line(name, e))


def _line(name: str, e: dict) -> str:
    lat, err = e["latency_s"], e["pose_error"] or {}
    ratio = e["rms_ratio"] or {}
    return (f"{name}: {e['frames']} frames of {e['sequence']} ({e['setting']}), "
            f"{e['fps']:.1f} frames/s ({e['fps_after_first'] or 0:.1f} after the first), "
            f"latency p50 {1000 * lat['p50']:.1f} ms p95 {1000 * lat['p95']:.1f} ms max "
            f"{1000 * lat['max']:.1f} ms; {e['runs_per_frame']} run(s) a frame, "
            f"{e['in_flight']} in flight, dropped {e['dropped']}, lost {e['lost']}\n"
            f"  against OpenCV: RMS ratio median {ratio.get('median', math.nan):.4f} max "
            f"{ratio.get('max', math.nan):.4f}, within {100 * (e['within'] or 0):.1f} % "
            f"of frames, pose {err.get('deg_max', math.nan):.3f} deg and "
            f"{100 * err.get('rel_max', math.nan):.3f} % of depth at most; client CPU "
            f"{1000 * (e['client_cpu_s_per_frame'] or 0):.2f} ms a frame (OpenCV's solve "
            f"{1000 * e['opencv_cpu_s_per_frame']:.3f} ms); {e['scheme']}, {e['engine']}")

