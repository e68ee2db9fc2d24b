"""``snail-client localize`` (contract: shared/FORMATS.md) and what ``track``
(track_cmd.py) shares with it: the options, the output, the exit statuses.

Exit status: 0 success (not converging is reported, not a failure), 1 the run failed
(network, server, integrity: then the record's ``error`` names the party to blame,
audit.py), 2 bad usage or bad input, with one line naming the field.
"""

from __future__ import annotations

import contextlib
import json
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import click
import numpy as np

from snail_common.loc.problem import ProblemError
from snail_common.loc.trust import DEFAULT_MAX_RMS_PX
from snail_common.net.linkrates import AUTO, CLIENT_SCHEMES
from snail_common.net.tls import TLSFileError

from . import owner_localize
from .audit import DEFAULT_AUDIT_RATE, IntegrityFailure
from .inputs.options import load_frame, localize_inputs
from .links import DEFAULT_LINK_TIMEOUT, ServiceError
from .localize import BACKENDS, Options, backend_for, failure_record, localize
from .progress import bar
from .relay import EVALUATOR
from .secure import DEFAULT_BUSY_WAIT
from .verbosity import flags as _verbosity


def _options(fn: Callable) -> Callable:
    """The options localize and track share."""
    decorators = [
        click.option("--algorithm", type=click.Choice(["lm", "gn"]), default="lm",
                     show_default=True, help="Levenberg-Marquardt or Gauss-Newton."),
        click.option("--mode", type=click.Choice(["sil", "do"]), default="sil",
                     show_default=True,
                     help="sil: one secure run per iteration, the client drives LM/GN; do: "
                          "the paper's data-oblivious baseline, a fixed number of LM "
                          "iterations in one (much larger) circuit, one run per frame."),
        click.option("--do-iterations", type=click.IntRange(1, 99), default=20,
                     show_default=True,
                     help="LM iterations inside the --mode do circuit (the paper uses 20)."),
        click.option("--solve", type=click.Choice(["client", "circuit"]),
                     help="Where the 6x6 step is solved. client (default for sil): the "
                          "circuit returns the normal equations, which are functions of "
                          "your own inputs, and the client damps and solves them: a "
                          "shallower circuit, and a rejected LM step costs no secure run. "
                          "circuit (forced for do): the paper's in-circuit solve."),
        click.option("--arith", type=click.Choice(["fixed", "float"]),
                     help="Per-point arithmetic of a --mode sil circuit. fixed "
                          "(default): the Jacobian and the sums over points in integers, "
                          "residuals and cost in float32 (0.18 M AND gates at n = 6 with "
                          "the client's solve); float: the same sums in narrow floats "
                          "(0.36 M). --solver svd is float only."),
        click.option("--solver", type=click.Choice(["ldlt", "svd"]), default="ldlt",
                     show_default=True, help="6x6 solver inside the circuit (--solve "
                                             "circuit)."),
        click.option("--backend", type=click.Choice(BACKENDS), default="garbled",
                     show_default=True,
                     help="garbled: the private service; cleartext: the same circuit in the "
                          "clear; float64: the plain reference solver (debugging only)."),
        click.option("--max-iterations", type=click.IntRange(1, 1000), default=20,
                     show_default=True, help="LM/GN iterations per frame at most."),
        click.option("--min-invocations", type=click.IntRange(0, 10000), default=20,
                     show_default=True,
                     help="Secure runs per frame at least (padded with dummy runs) so the "
                          "servers cannot tell how fast it converged. --mode do makes "
                          "exactly one run per frame whatever the data, and is not padded."),
        click.option("--pad-points", type=click.IntRange(0, 4096), default=0,
                     show_default=True,
                     help="Round the number of points up to a multiple of this with "
                          "zero-weight dummies, hiding the exact count (0: no padding)."),
        click.option("--garbler", metavar="HOST:PORT",
                     help="Garbler address (default: start both servers on loopback)."),
        click.option("--evaluator", metavar="HOST:PORT", help="Evaluator address."),
        click.option("--tls-dir", type=click.Path(file_okay=False, exists=True),
                     help="Directory with ca.pem and the client certificate and key."),
        click.option("--cert-name", default="client", show_default=True, metavar="NAME",
                     help="Client certificate to use from --tls-dir (NAME.pem, NAME.key), "
                          "e.g. one made by 'snail-client certs DIR --client NAME'."),
        click.option("--max-rms-px", type=click.FloatRange(0, min_open=True),
                     default=DEFAULT_MAX_RMS_PX, show_default=True,
                     help="A pose whose reprojection RMS is above this is reported as "
                          "bad_fit (exit 3), not converged."),
        click.option("--busy-wait", type=click.FloatRange(0, 3600),
                     default=DEFAULT_BUSY_WAIT, show_default=True, metavar="SECONDS",
                     help="How long a secure run retries servers that answer busy (at "
                          "their session limit), with jittered backoff, before failing."),
        click.option("--scheme", type=click.Choice(list(CLIENT_SCHEMES)),
                     default=AUTO, show_default=True,
                     help="Garbling scheme: three-halves (Rosulek-Roy 2021) sends 0.77x the "
                          "garbled-table bytes of half-gates but garbles slower: worth it "
                          "on a slow garbler-evaluator link. auto: per session, from the "
                          "server link's rate and the garbler's own, as the garbler "
                          "measured them (half-gates until it has)."),
        click.option("--link-timeout", type=click.FloatRange(1, 3600),
                     default=DEFAULT_LINK_TIMEOUT, show_default=True, metavar="SECONDS",
                     help="A server link a run waits on is probed after a fifth of this "
                          "in silence and given up (the run fails, naming the link) after "
                          "this long: a partition or a stalled server."),
        click.option("--audit-rate", type=click.FloatRange(0, 1), default=DEFAULT_AUDIT_RATE,
                     show_default=True, metavar="P",
                     help="Share of secure runs the client garbles again itself from its "
                          "own seed and offset, to catch a garbler whose tables or "
                          "zero-labels are not the circuit's (drawn at random per run; "
                          "every run that fails the integrity check is audited too). "
                          "Nothing the servers see tells them which runs were audited."),
        click.option("--evidence", type=click.Path(file_okay=False), metavar="DIR",
                     help="Write a snail-evidence/1 file here when an audit catches the "
                          "garbler: anyone can check it with 'snail-bench verify-evidence'."),
        click.option("--json", "as_json", is_flag=True,
                     help="Print the snail-result/1 JSON record(s) instead of a summary."),
        click.option("--output", type=click.Path(dir_okay=False, writable=True),
                     help="Also write the result JSON to this file."),
    ]
    for decorate in reversed(decorators):
        fn = decorate(fn)
    return fn


relay_option = click.option(
    "--relay", is_flag=False, flag_value=EVALUATOR, metavar="[HOST:PORT]",
    help="Map-owner setting: reach the map owner through this evaluator (the flag alone: "
         "the evaluator the runs go to), never directly, so that the map owner sees the "
         "evaluator's address, not yours. Your TLS with the map owner runs end to end "
         "inside: the evaluator cannot read it. Its operator must allow the map owner "
         "(snail-evaluator --map-owner).")


def check_relay(options: Options, owner: bool) -> None:
    """UsageError for a --relay that leads nowhere (no map owner to reach)."""
    if options.relay and not owner:
        raise click.UsageError("--relay: with --map-owner or --map (it is the way to the "
                               "map owner)")


def _make_options(kw: dict) -> Options:
    try:
        return Options(**{k: kw[k] for k in (
            "algorithm", "mode", "solver", "backend", "max_iterations", "min_invocations",
            "pad_points", "garbler", "evaluator", "tls_dir", "do_iterations",
            "busy_wait", "max_rms_px", "cert_name", "solve", "link_timeout",
            "scheme", "arith", "audit_rate", "evidence", "relay")})
    except ValueError as e:
        raise click.UsageError(str(e)) from None


def _summary(record: dict) -> str:
    """Pose, fit, work and cost in three lines. The pace is the median timed secure call:
    the first call of a fresh daemon also loads the circuit, padding runs are not timed."""
    t = record["traffic"]
    mb = t["garbler_to_evaluator"] / 1e6
    walls = record["timing"]["per_iteration_s"]
    pace = (f"; {len(walls)} timed calls, median {float(np.median(walls)):.3f} s, "
            f"first {walls[0]:.3f} s" if walls else "")
    state = record["status"].replace("_", " ")
    return (f"rvec {np.round(record['rvec'], 6).tolist()}  tvec "
            f"{np.round(record['tvec'], 6).tolist()}\n"
            f"rms {record['rms_px']:.4f} px  {state} after {record['iterations']} iterations "
            f"({record['invocations']} invocations, {record['backend']})\n"
            f"time {record['timing']['total_s']:.2f} s{pace}  "
            f"garbler->evaluator {mb:.1f} MB, client sent "
            f"{(t['client_to_garbler'] + t['client_to_evaluator']) / 1e3:.1f} kB")


def _fail(code: int, message: str) -> None:
    click.echo(f"snail-client: {message}", err=True)
    sys.exit(code)


def _worse(a: int, b: int) -> int:
    """Exit statuses by weight: a failed run (1) over an untrusted frame (3) over 0."""
    return 1 if 1 in (a, b) else max(a, b)


def _untrusted(record: dict, where: str = "") -> str:
    """The one stderr line for a pose that came back but is not trusted."""
    reasons = "; ".join(record["warnings"]) or record["status"]
    return f"{where}pose not trusted ({record['status']}): {reasons}"


def _write(output: str | None, records: list[dict], single: bool) -> None:
    if output:
        payload = records[0] if single and records else records
        Path(output).write_text(json.dumps(payload, indent=1) + "\n")


def _result_line(record: dict) -> str:
    """-q's answer: the pose and its status on one line."""
    return (f"rvec {np.round(record['rvec'], 6).tolist()}  tvec "
            f"{np.round(record['tvec'], 6).tolist()}  {record['status']}")


def _show(record: dict, as_json: bool) -> None:
    """The result as JSON, one line (-q) or the summary; -v adds the costs on stderr."""
    if as_json:
        click.echo(json.dumps(record))
    elif _verbosity().get("quiet"):
        click.echo(_result_line(record))
    else:
        click.echo(_summary(record))
    if _verbosity().get("verbose"):
        t, walls = record["traffic"], record["timing"]["per_iteration_s"]
        click.echo(f"snail-client: {record['invocations']} secure runs "
                   f"({len(walls)} timed: {', '.join(f'{w:.3f}' for w in walls)} s), "
                   f"{record['timing']['total_s']:.2f} s in all, bytes per link {t}",
                   err=True)


@contextlib.contextmanager
def _progress(backend: object, total: int, desc: str) -> Iterator[None]:
    """A bar of secure runs on a terminal (a garbled backend reports each one)."""
    if not hasattr(backend, "on_invocation"):
        yield
        return
    with bar(total, desc, _verbosity().get("quiet", False), unit="run") as b:
        backend.on_invocation = b.update
        try:
            yield
        finally:
            backend.on_invocation = None


@click.command("localize")
@localize_inputs
@_options
@click.option("--map-owner", metavar="HOST:PORT",
              help="Map-owner setting: --input is a snail-frame/1 (2D points and the ids of "
                   "the map points they match) and the map stays with the map owner "
                   "(snail-mapd) at this address; it never learns your ids, points or "
                   "pose, you never see its 3D points. Needs --garbler, --evaluator and "
                   "--tls-dir.")
@click.option("--map", "map_path", type=click.Path(exists=True, dir_okay=False),
              metavar="MAP.json",
              help="Map-owner setting with a map owner started here on loopback with this "
                   "snail-map/1 map, for trying it out: this gives NO privacy against "
                   "yourself (this machine holds the map and the frame together).")
@relay_option
def localize_cmd(input_path: str | None, as_json: bool, output: str | None,
                 map_owner: str | None, map_path: str | None, **kw) -> None:
    """Find the camera pose of one image privately: from a problem file, a camera image
    with AprilTags, or an image of a COLMAP model; or, with --map-owner/--map, from a
    frame whose map points only a map owner holds.

    Exit status: 0 a trusted pose; 1 the run failed; 2 bad usage or input; 3 a pose came
    back but is not trusted (status not_converged, degenerate, bad_fit or behind_camera;
    one line on stderr says why)."""
    options = _make_options(kw)
    check_relay(options, bool(map_owner or map_path))
    if map_owner or map_path:
        if not input_path or kw.get("image") or kw.get("colmap"):
            raise click.UsageError("--map-owner/--map take a snail-frame/1 file as --input")
        try:
            owner_localize.check(options, map_owner, map_path)
        except ValueError as e:
            raise click.UsageError(str(e)) from None
    else:
        try:
            input_path, problem = load_frame(input_path, kw)
        except ProblemError as e:
            _fail(2, str(e))
    try:
        if map_owner or map_path:
            record = owner_localize.localize_frame(input_path, options, map_owner, map_path)
        else:
            with backend_for(options) as backend, _progress(
                    backend, max(options.min_invocations, 1), "secure runs"):
                record = localize(problem, options, backend)
    except TLSFileError as e:
        _fail(2, f"--tls-dir: {e}")
    except (ProblemError, ValueError) as e:
        _fail(2, str(e) if map_owner or map_path else f"{input_path}: {e}")
    except IntegrityFailure as e:  # no pose: the party to blame, in the record too
        failed = failure_record(e, options)
        if as_json:
            click.echo(json.dumps(failed))
        _write(output, [failed], single=True)
        _fail(1, str(e))
    except ServiceError as e:
        _fail(1, str(e))
    except KeyboardInterrupt:
        _fail(130, "interrupted")
    _show(record, as_json)
    _write(output, [record], single=True)
    if record["status"] != "converged":
        _fail(3, _untrusted(record))
