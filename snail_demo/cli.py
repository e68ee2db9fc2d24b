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
              help="Folder for turbo.json, turbo.mp4 and trajectory.png (created).")
@click.option("--backend", type=click.Choice(["garbled", "cleartext"]), default="garbled",
              show_default=True,
              help="garbled: both servers on loopback, TLS; cleartext: the same circuits "
                   "evaluated in the clear (same poses, no servers).")
@click.option("--link-delay-ms", type=click.FloatRange(0, 10000), default=0.0,
              show_default=True,
              help="Simulated one-way delay of the client's links: each secure run waits "
                   "one extra round trip (2 D ms). For links really shaped with tc, run "
                   "the daemons in the network lab and pass their addresses to the API.")
@click.option("--min-invocations", type=click.IntRange(0, 10000), default=20,
              show_default=True,
              help="Secure runs per frame at least (padding), as in snail-client track: "
                   "every frame costs the same, whatever its iterations.")
@click.option("--max-steps", type=click.IntRange(1, 1000), default=80, show_default=True,
              help="Control steps at most.")
@click.option("--seed", type=int, default=3, show_default=True,
              help="Seed of image noise and wheel slip.")
def turbo(out_dir: str, backend: str, link_delay_ms: float, min_invocations: int,
          max_steps: int, seed: int) -> None:
    """Turbo the snail robot drives to a target pose on private localization.

    Writes DIR/turbo.json (one record per control step and the final errors),
    DIR/turbo.mp4 (camera view with detected tags and the estimated pose, beside a
    top-down map of true and estimated paths) and DIR/trajectory.png. Exit status 0 when
    the robot ends within 2 cm and 2 degrees of the target, else 3."""
    from .turbo_run import run_turbo  # imports the drawing only for this command

    if link_delay_ms and backend != "garbled":
        raise click.UsageError("--link-delay-ms: only with --backend garbled (cleartext has "
                               "no links)")

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
