"""snail-demo: demonstrations on rendered camera images."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from snail_client.localize import Options, backend_for
from snail_client.progress import bar
from snail_client.verbosity import VerbosityGroup

from .accuracy import POSITION_FRAC, ROTATION_DEG, sweep


@click.group(cls=VerbosityGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="snail", prog_name="snail-demo")
@click.option("-v", "--verbose", is_flag=True,
              help="Also say on stderr what each control step or frame gave.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bars.")
@click.pass_context
def main(ctx: click.Context, verbose: bool, quiet: bool) -> None:
    """Private localization from rendered AprilTag images."""
    if verbose and quiet:
        raise click.UsageError("-v and -q: choose one")
    ctx.obj = {"verbose": verbose, "quiet": quiet}


def _flag(name: str) -> bool:
    return bool((click.get_current_context().find_object(dict) or {}).get(name))


@main.command()
@click.option("--frames", type=click.IntRange(1, 100000), default=200, show_default=True,
              help="Random scenes to render and localize.")
@click.option("--seed", type=int, default=1, show_default=True, help="Scene generator seed.")
@click.option("--backend", type=click.Choice(["cleartext", "float64", "garbled"]),
              default="cleartext", show_default=True,
              help="cleartext: the garbled circuit's exact output without the servers; "
                   "float64: the plain reference; garbled: through embedded daemons.")
@click.option("--json", "as_json", is_flag=True, help="Print the whole report as JSON.")
def accuracy(frames: int, seed: int, backend: str, as_json: bool) -> None:
    """How often the image path's pose matches cv2.solvePnP on the same detections (from
    the same IPPE first pose) within 0.5 % of the camera distance and 0.5 degrees: tags at
    20-70 degrees of obliquity, blur, noise and lens distortion."""
    options = Options(backend=backend, min_invocations=0)
    with backend_for(options) as runner, bar(frames, "frames", _flag("quiet"),
                                              "frame") as progress:
        report = sweep(frames, seed, options, runner, progress)
    if as_json:
        click.echo(json.dumps(report, indent=1))
        return
    pct = report["percentiles"]
    click.echo(f"{report['matches_opencv']}/{report['detected']} detected frames "
               f"({100 * report['fraction_matching_opencv']:.1f} %) within "
               f"{100 * POSITION_FRAC:g} % and {ROTATION_DEG:g} deg of OpenCV; "
               f"{report['not_detected']} of {frames} without a detected tag")
    for key, values in pct.items():
        click.echo(f"  {key}: p50 {values['p50']:.3g}  p99 {values['p99']:.3g}  "
                   f"max {values['max']:.3g}")


@main.command()
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Folder for turbo.json, turbo.mp4 and trajectory.png (created); with "
                   "--realtime also turbo.gif.")
@click.option("--backend", type=click.Choice(["garbled", "cleartext"]), default="garbled",
              show_default=True,
              help="garbled: both servers on loopback, TLS; cleartext: the same circuits "
                   "evaluated in the clear (same poses, no servers).")
@click.option("--realtime", is_flag=True,
              help="Drive on the wall clock: the robot keeps moving at --speed while each "
                   "pose is computed; the camera takes frames at --camera-fps from the "
                   "robot's true pose at capture, each frame gets one secure run after the "
                   "padded first (Localizer.track, Turbo's commanded motion as odometry), "
                   "and the controller steers on every pose as it arrives, moved by the "
                   "odometry since its capture to where the robot is now. Reached: within "
                   "1 cm and 1 degree.")
@click.option("--speed", type=click.FloatRange(0.01, 2.0), default=None,
              help="--realtime: the robot's cruising speed in m/s (it slows down only for "
                   "the last tens of centimetres).  [default: 0.3]")
@click.option("--camera-fps", type=click.FloatRange(1, 240), default=None,
              help="--realtime: the camera's frame rate; the tracker takes the newest frame "
                   "each time it is ready for one.  [default: 30]")
@click.option("--max-seconds", type=click.FloatRange(1, 3600), default=None,
              help="--realtime: stop the robot after this long on the clock.  [default: 60]")
@click.option("--runs-per-frame", type=click.IntRange(1, 20), default=None,
              help="--realtime: secure runs per frame after the first, one Gauss-Newton step each "
                   "(the fixed schedule: the servers see the same count every frame).  "
                   "[default: 1]")
@click.option("--link-delay-ms", type=click.FloatRange(0, 10000), default=0.0,
              show_default=True,
              help="Simulated one-way delay of the client's links: each secure run waits "
                   "one extra round trip (2 D ms); not with --realtime. For links really "
                   "shaped with tc, run the daemons in the network lab and pass their "
                   "addresses to the API.")
@click.option("--min-invocations", type=click.IntRange(0, 10000), default=20,
              show_default=True,
              help="Secure runs per frame at least (padding), as in snail-client track: "
                   "every frame costs the same, whatever its iterations. With --realtime: "
                   "the first frame's only.")
@click.option("--max-steps", type=click.IntRange(1, 1000), default=80, show_default=True,
              help="Control steps at most (without --realtime).")
@click.option("--seed", type=int, default=3, show_default=True,
              help="Seed of image noise and wheel slip.")
def turbo(out_dir: str, backend: str, realtime: bool, speed: float | None,
          camera_fps: float | None, max_seconds: float | None, runs_per_frame: int | None,
          link_delay_ms: float, min_invocations: int, max_steps: int, seed: int) -> None:
    """Turbo the snail robot drives to a target pose on private localization.

    Step by step (the paper's way): the robot moves at most 0.1 m, stops, takes an image
    and localizes it privately (padded to --min-invocations runs), then moves again.
    With --realtime it drives continuously (see --realtime); measured 2026-12-04 on two
    shared cores, garbled on loopback, --speed 0.3: at the target within 0.4 cm and 0.42
    degrees after 6.5-7.5 s of driving, 24-25 private poses a second, 56-58 ms from a
    frame's capture to its pose (p50; docs/images.md).

    Writes DIR/turbo.json (one record per control step or frame and the final errors;
    with --realtime the summary adds speed_mps, fps and latency_s, capture to pose),
    DIR/turbo.mp4 (camera view with detected tags and the estimated pose, beside a
    top-down map of true and estimated paths), DIR/trajectory.png and, with --realtime,
    DIR/turbo.gif. Exit status 0 when the robot ends within 2 cm and 2 degrees of the
    target (--realtime: 1 cm and 1 degree), else 3."""
    ctx = click.get_current_context()
    given = {name for name in ("speed", "camera_fps", "max_seconds", "runs_per_frame",
                               "link_delay_ms", "max_steps")
             if ctx.get_parameter_source(name) is not click.core.ParameterSource.DEFAULT}
    if not realtime and given & {"speed", "camera_fps", "max_seconds", "runs_per_frame"}:
        flag = sorted(given & {"speed", "camera_fps", "max_seconds", "runs_per_frame"})[0]
        raise click.UsageError(f"--{flag.replace('_', '-')}: only with --realtime")
    if realtime and given & {"link_delay_ms", "max_steps"}:
        flag = sorted(given & {"link_delay_ms", "max_steps"})[0]
        raise click.UsageError(f"--{flag.replace('_', '-')}: not with --realtime")
    if link_delay_ms and backend != "garbled":
        raise click.UsageError("--link-delay-ms: only with --backend garbled (cleartext has "
                               "no links)")
    if realtime:
        _turbo_realtime(Path(out_dir), backend, 0.3 if speed is None else speed,
                        30.0 if camera_fps is None else camera_fps,
                        60.0 if max_seconds is None else max_seconds, min_invocations,
                        runs_per_frame or 1, seed)
        return
    from .turbo_run import run_turbo  # imports the drawing only for this command

    final = run_turbo(Path(out_dir), backend, link_delay_ms, min_invocations, max_steps,
                      seed, quiet=_flag("quiet"), verbose=_flag("verbose"))
    later = ("no frame after the first" if final["median_invocations_after_first"] is None
             else f"{final['median_invocations_after_first']:g} secure runs per frame after "
                  f"the first ({final['median_iterations_after_first']:g} iterations)")
    click.echo(f"{'reached' if final['reached'] else 'missed'} the target in "
               f"{final['steps']} steps: {100 * final['position_error_m']:.2f} cm, "
               f"{final['rotation_error_deg']:.2f} deg off; median "
               f"{final['median_seconds_per_step']:.2f} s per step, {later}, client CPU "
               f"{final['median_client_cpu_s']:.2f} s per step; wrote {out_dir}")
    if not final["reached"]:
        sys.exit(3)


def _turbo_realtime(out: Path, backend: str, speed: float, camera_fps: float,
                    max_seconds: float, min_invocations: int, runs_per_frame: int,
                    seed: int) -> None:
    from .turbo_run import run_turbo_realtime

    final = run_turbo_realtime(out, backend, speed, camera_fps, max_seconds, min_invocations,
                               runs_per_frame, seed, quiet=_flag("quiet"),
                               verbose=_flag("verbose"))
    latency = final["latency_s"]
    click.echo(f"{'reached' if final['reached'] else 'missed'} the target after "
               f"{final['drive_s']:.1f} s driving at up to {speed:g} m/s: "
               f"{100 * final['position_error_m']:.2f} cm, "
               f"{final['rotation_error_deg']:.2f} deg off; {final['steps']} private poses "
               f"({final['runs_first_frame']} secure runs for the first, then "
               f"{'/'.join(map(str, final['runs_after_first'])) or 'none'} a frame) at "
               f"{final['fps'] or 0:.1f} frames/s, pose {1000 * latency['p50']:.0f} ms after "
               f"capture (p95 {1000 * latency['p95']:.0f} ms); wrote {out}")
    if not final["reached"]:
        sys.exit(3)
