"""``snail-client track``: a stream of frames on the fixed schedule (contract:
shared/FORMATS.md, round 4), standing on ``tracking.Tracker`` as ``Localizer.track`` does.

Inputs: ``--input`` (a sequence of snail-problem/1), ``--image-dir`` (camera images with
AprilTags), or with ``--map``/``--map-owner`` a sequence of snail-frame/1 (the map-owner
setting). Output: one record per frame (JSON with ``--json``, one line each, then a
``{"summary": ...}`` line; ``--output`` gets the list of records), a live progress line on
stderr (a terminal only) and a summary. Exit status: 0 every frame trusted, 1 a secure
run failed, 2 the sequence or a flag is bad, 3 some frame failed or is not trusted.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import sys
import time
from collections.abc import Iterator

import click
import numpy as np

from snail_common.loc.mapfile import parse_frame
from snail_common.loc.problem import ProblemError, read_sequence
from snail_common.loc.schedule import MOTION_MODELS, ON_LOST
from snail_common.loc.trust import TRUSTED
from snail_common.net.tls import TLSFileError

from . import owner_localize
from .inputs.options import load_frames, track_inputs
from .links import ServiceError
from .localize import MAX_IN_FLIGHT, Options, backend_for
from .localize_cmd import (
    _fail,
    _make_options,
    _options,
    _result_line,
    _untrusted,
    _write,
    check_relay,
    relay_option,
)
from .progress import bar
from .track_frames import MapFrames, Problems
from .tracking import Item, Tracker, summary
from .verbosity import flags as _verbosity


def _tracking_options(fn):
    """The schedule's flags (the figures quoted are this machine's: docs/performance.md,
    tracking)."""
    decorators = [
        click.option("--runs-per-frame", type=click.IntRange(0, 100), default=1,
                     show_default=True, metavar="K",
                     help="After the first frame's padded localization (--min-invocations "
                          "runs), every frame gets exactly K secure runs, each one "
                          "--step from the prediction (the last trusted pose, moved by "
                          "--motion-model): the servers see the same count whatever the "
                          "data. 0: pad every frame to --min-invocations, as before. At "
                          "n = 6 one run a "
                          "frame followed a 30 frames/s hand-held walk at 82-85 frames/s on "
                          "a 2-core machine running both servers, 99.7 % of frames within "
                          "1 % of OpenCV's RMS (snail-bench track, 2026-12-04); 2 runs land "
                          "on the converged pose."),
        click.option("--in-flight", type=click.IntRange(1, MAX_IN_FLIGHT), metavar="D",
                     help="Frames whose runs may overlap: a frame starts from the pose of "
                          "the frame D before it, so a slow client link costs throughput, "
                          "not frames. Default: from the first frame's runs, 1 + a run's "
                          "client round trip over the servers' part of it (garbling, "
                          "evaluation or the tables on the server link): 1 on loopback, 1-2 "
                          "under the network lab's region profile (24.3-24.4 frames/s at "
                          "n = 6 there)."),
        click.option("--rate", type=click.FloatRange(0, min_open=True), metavar="R",
                     help="Secure runs at R per second whatever the frames: a slot no frame "
                          "takes runs padding the servers cannot tell from a frame, so frame "
                          "timing and dropped frames are hidden too (garbled only)."),
        click.option("--on-lost", type=click.Choice(ON_LOST), default="wait",
                     show_default=True,
                     help="A lost track (RMS above --max-rms-px, points behind the camera): "
                          "wait re-localizes within the frames' own K runs, from the lost "
                          "answer while it improves; reveal gives the next frame a padded "
                          "localization, which the servers can tell (its record says "
                          "revealed)."),
        click.option("--step", type=click.Choice(["gn", "lm"]), default="gn",
                     show_default=True,
                     help="What each of a frame's K runs steps by: Gauss-Newton, or LM "
                          "(damped: from a nearby prediction its one step falls short; "
                          "--algorithm is the padded first frame's)."),
        click.option("--motion-model", type=click.Choice(MOTION_MODELS), default="auto",
                     show_default=True,
                     help="Predict each frame from the last trusted pose (none), move it "
                          "by the last two frames' motion (constant-velocity), or take "
                          "whichever of the two has been nearer the stream's recent answers "
                          "(auto). Your own choice, from your own answers: the servers see "
                          "the same runs."),
    ]
    for decorate in reversed(decorators):
        fn = decorate(fn)
    return fn


@click.command("track")
@track_inputs
@click.option("--map-owner", metavar="HOST:PORT",
              help="Map-owner setting: --input is a sequence of snail-frame/1, the map "
                   "stays with the map owner at this address (needs --garbler, --evaluator "
                   "and --tls-dir); each frame's points are selected from it by OT.")
@click.option("--map", "map_path", type=click.Path(exists=True, dir_okay=False),
              metavar="MAP.json",
              help="Map-owner setting with a map owner started here with this snail-map/1 "
                   "map, for trying it out (no privacy against yourself).")
@relay_option
@click.option("--fail-fast", is_flag=True,
              help="Stop at the first frame that fails or is not trusted.")
@_tracking_options
@_options
def track_cmd(input_path: str | None, as_json: bool, output: str | None, fail_fast: bool,
              map_owner: str | None, map_path: str | None, runs_per_frame: int,
              in_flight: int | None, rate: float | None, on_lost: str, step: str,
              motion_model: str, **kw) -> None:
    """Follow a sequence privately: the first frame padded, every later one exactly
    --runs-per-frame secure runs from the last trusted pose.

    Each record adds runs, latency_s, track_status (tracking, lost or relocalized),
    revealed (something data-dependent changed what the servers saw) and prediction
    (what moved its start: odometry, constant-velocity or last-pose). A frame that
    cannot be read is named on stderr, recorded with its failure, and still makes its
    runs (padding); --output always gets what was computed. Exit status: 0 every frame
    trusted; 1 a secure run failed; 2 the sequence cannot be read; 3 some frame failed or
    is not trusted."""
    try:
        options = dataclasses.replace(_make_options(kw), runs_per_frame=runs_per_frame,
                                      in_flight=in_flight, rate=rate, on_lost=on_lost,
                                      step=step, motion_model=motion_model)
    except ValueError as e:
        raise click.UsageError(str(e)) from None
    owner = bool(map_owner or map_path)
    check_relay(options, owner)
    if owner:
        if not input_path or kw.get("image_dir"):
            raise click.UsageError("--map-owner/--map take a sequence of snail-frame/1 as "
                                   "--input")
        try:
            owner_localize.check(options, map_owner, map_path)
        except ValueError as e:
            raise click.UsageError(str(e)) from None
    try:
        frames = (read_sequence(input_path, parse_frame) if owner
                  else load_frames(input_path, kw))
    except ProblemError as e:
        _fail(2, str(e))
    records: list[dict] = []
    worst = 0
    try:
        with _solver(options, map_owner, map_path, owner) as (backend, solver):
            worst = _follow(Tracker(options, backend, solver), frames, records, as_json,
                            fail_fast)
    except ServiceError as e:  # connecting or closing, outside any frame
        worst = 1
        click.echo(f"snail-client: {e}", err=True)
    except TLSFileError as e:
        worst = 2
        click.echo(f"snail-client: --tls-dir: {e}", err=True)
    except ProblemError as e:  # the map of --map
        worst = 2
        click.echo(f"snail-client: {e}", err=True)
    except KeyboardInterrupt:
        worst = 130
        click.echo(f"snail-client: interrupted after {len(records)} frames (--output keeps "
                   f"them)", err=True)
    finally:
        _write(output, records, single=False)
    if worst:
        sys.exit(worst)


@contextlib.contextmanager
def _solver(options: Options, map_owner: str | None, map_path: str | None,
            owner: bool) -> Iterator[tuple]:
    if owner:
        with owner_localize.session(options, map_owner, map_path) as (backend, link, known):
            yield backend, MapFrames(options, link, known)
    else:
        with backend_for(options) as backend:
            yield backend, Problems(options)


def _follow(tracker: Tracker, frames: list, records: list[dict], as_json: bool,
            fail_fast: bool) -> int:
    """Run the stream, show each frame and the summary; the exit status so far."""
    quiet = _verbosity().get("quiet", False)
    worst = 0
    began, cpu = time.perf_counter(), time.process_time()
    items = (Item(name, source) for name, source in frames)
    with bar(len(frames), "frames", quiet, "frame") as progress:
        for out, _ in tracker.run(items):
            records.append(out)
            progress.update(1)
            latencies = [r["latency_s"] for r in records[-30:]]
            progress.set_postfix_str(f"latency p50 {1000 * float(np.median(latencies)):.0f} "
                                     f"ms, {out['track_status']}")
            bad = _report(out, as_json, quiet)
            if bad:
                worst = 1 if 1 in (worst, bad) else max(worst, bad)
                if fail_fast:
                    break
    totals = summary(records, time.perf_counter() - began, time.process_time() - cpu,
                     tracker)
    if as_json:
        click.echo(json.dumps({"summary": totals}))
    elif not quiet:
        click.echo(_summary_text(totals))
    return worst


def _report(out: dict, as_json: bool, quiet: bool) -> int:
    """Print a frame; 0, or the exit status it asks for (1 failed runs, 3 untrusted)."""
    where = f"frame {out['frame']} ({out['input']}): "
    if "failure" in out:
        click.echo(f"snail-client: {where}{out['failure']}", err=True)
        if as_json:
            click.echo(json.dumps(out))
        return 1 if out.get("service_error") else 3
    if as_json:
        click.echo(json.dumps(out))
    elif quiet:
        click.echo(_result_line(out))
    else:
        click.echo(f"frame {out['frame']}: rvec {np.round(out['rvec'], 6).tolist()}  tvec "
                   f"{np.round(out['tvec'], 6).tolist()}  {out['status']}, rms "
                   f"{out['rms_px']:.3f} px, {_runs(out['runs'])}, "
                   f"{1000 * out['latency_s']:.1f} ms, {out['track_status']}"
                   + (", revealed" if out["revealed"] else ""))
    if out["status"] not in TRUSTED:
        click.echo(f"snail-client: {where}{_untrusted(out)}", err=True)
        return 3
    return 0


def _counts(counts: dict[str, int]) -> str:
    return ", ".join(f"{name} {count}" for name, count in sorted(counts.items()))


def _runs(count: int) -> str:
    return f"{count} run" + ("" if count == 1 else "s")


def _summary_text(s: dict) -> str:
    lat = s["latency_s"]
    after = ", ".join(map(str, s["runs_after_first"])) or "-"
    return (f"{s['frames']} frames in {s['wall_s']:.2f} s: {s['fps']:.1f} frames/s, latency "
            f"p50 {1000 * lat['p50']:.1f} ms, p95 {1000 * lat['p95']:.1f} ms, max "
            f"{1000 * lat['max']:.1f} ms\n"
            f"runs: {s['runs_first_frame']} for the first frame, {after} for each later one "
            f"(--runs-per-frame {s['runs_per_frame']}), {s['in_flight']} in flight; "
            f"lost {s['lost']}, relocalized {s['relocalized']}, revealed {s['revealed']}\n"
            + (f"predicted by: {_counts(s['predictions'])} (the client's choice, unseen "
               "by the servers)\n" if s.get("predictions") else "")
            + f"the servers saw: circuit {s['circuit']}, the runs above"
            + (f" at {s['rate']:g} per second" if s["rate"] else ", at the frames' pace")
            + f"; client CPU {1000 * s['client_cpu_s_per_frame']:.2f} ms a frame")
