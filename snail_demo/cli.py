"""snail-demo: demonstrations on rendered camera images."""

from __future__ import annotations

import json

import click

from snail_client.localize import Options, backend_for
from snail_client.progress import bar

from .accuracy import POSITION_FRAC, ROTATION_DEG, sweep


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="snail", prog_name="snail-demo")
def main() -> None:
    """Private localization from rendered AprilTag images."""


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
    with backend_for(options) as runner, bar(frames, "frames", False, "frame") as progress:
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
