"""snail-bench: measure what the budgets and targets in DESIGN.md talk about."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path

import click
import numpy as np

from snail_client.verbosity import VerbosityGroup
from snail_common import families
from snail_common.circuit import evaluate_bits, schedule_circuit
from snail_common.circuit.bristol import BristolError, load_bristol
from snail_common.gc.stream import SCHEMES
from snail_common.net.linkrates import AUTO, CLIENT_SCHEMES

from .choices import SERVICE_POINTS
from .choices import spec as _spec
from .netcmd import netem, paper


def _parse_int(text: str) -> int:
    try:
        return int(text, 0)
    except ValueError:
        raise click.BadParameter(f"{text!r} is not an integer (decimal or 0x-hex)") from None


def _emit(report: dict, as_json: bool) -> None:
    """Print a one-section report as JSON (the FORMATS contract) or as aligned lines."""
    if as_json:
        click.echo(json.dumps(report))
        return
    for key, value in next(iter(report.values())).items():
        if isinstance(value, dict) and value and all(isinstance(v, dict)
                                                     for v in value.values()):
            for name, fields in value.items():  # one line per entry, its plain fields
                plain = "  ".join(f"{k} {v}" for k, v in fields.items()
                                  if not isinstance(v, dict))
                click.echo(f"{key + ' ' + name:>24}: {plain}")
            continue
        if isinstance(value, dict):
            value = "  ".join(f"{k} {v}" for k, v in value.items())
        click.echo(f"{key:>24}: {value}")


ACCURACY_TARGETS = {"lm": 0.999, "gn": 0.99}  # pass rates `accuracy` holds the loop to
# on the hard kinds, against float64 (issue 32): LM all, GN 99.5 % (client) and 99 %
HARD_TARGETS = {("lm", "client"): 1.0, ("lm", "circuit"): 1.0, ("gn", "client"): 0.995,
                ("gn", "circuit"): 0.99}



@click.group(cls=VerbosityGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="snail", prog_name="snail-bench")
@click.option("-v", "--verbose", is_flag=True, help="Report each measurement on stderr "
                                                    "as it finishes.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bars.")
@click.pass_context
def main(ctx: click.Context, verbose: bool, quiet: bool) -> None:
    """Benchmarks and gate counts of snail's circuits and engines."""
    families.register_all()
    ctx.obj = {"verbose": verbose, "quiet": quiet}


main.add_command(netem)  # the network lab and the paper's figures: netcmd.py
main.add_command(paper)


# --arith of circuit, service and accuracy
ARITH = click.option("--arith", type=click.Choice(["fixed", "float"]),
                     help="Per-point arithmetic of a SIL circuit: fixed (default; integer "
                          "Jacobian and sums, float32 residuals and cost) or float (narrow "
                          "floats). DO and SVD circuits are float.")


@main.command()
@click.argument("file", type=click.Path(exists=True, dir_okay=False))
@click.option("--input", "inputs", multiple=True, required=True, metavar="INT",
              help="One input value of the file, in order: an integer (decimal or 0x-hex) "
                   "whose bit i is the value's wire i. Repeat once per input value.")
@click.option("--garbled", is_flag=True,
              help="Garble and evaluate with half-gates (fresh seed and delta) instead of "
                   "evaluating in the clear.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def bristol(file: str, inputs: tuple[str, ...], garbled: bool, as_json: bool) -> None:
    """Run a Bristol Fashion circuit FILE and print its outputs."""
    try:
        circuit = load_bristol(file)
    except BristolError as e:
        raise click.UsageError(f"{file}: {e}") from None
    if len(inputs) != len(circuit.inputs):
        raise click.UsageError(f"{file} takes {len(circuit.inputs)} --input values, "
                               f"got {len(inputs)}")
    bits = []
    for group, text in zip(circuit.inputs, inputs):
        value = _parse_int(text)
        if value < 0:
            value &= (1 << group.bits) - 1  # two's complement
        if value >> group.bits:
            raise click.UsageError(f"--input {text} does not fit in {group.bits} bits")
        bits.extend((value >> i) & 1 for i in range(group.bits))
    schedule = schedule_circuit(circuit)
    if garbled:
        from snail_common.gc.run import garbled_run

        out_bits = np.asarray(garbled_run(schedule, np.array(bits, bool))).reshape(-1)
    else:
        out_bits = evaluate_bits(schedule, np.array([bits], bool))[0]
    outputs, pos = [], 0
    for group in circuit.output_groups:
        chunk = out_bits[pos : pos + group.bits]
        pos += group.bits
        outputs.append(sum(1 << i for i, bit in enumerate(chunk) if bit))
    counts = circuit.counts()
    result = {"outputs": outputs, **counts, "depth": circuit.depth(), "garbled": garbled}
    if as_json:
        click.echo(json.dumps({"bristol": result}))
    else:
        click.echo(" ".join(str(v) for v in outputs))
        click.echo(f"AND {counts['and']}  XOR {counts['xor']}  NOT {counts['not']}  "
                   f"depth {circuit.depth()}", err=True)


@main.command()
@click.option("--gates", default=50_000_000, show_default=True,
              help="Approximate size of the generated circuit.")
@click.option("--lane-words", default=1, show_default=True,
              help="64-bit words of input vectors per wire in the cleartext run.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def compiler(gates: int, lane_words: int, as_json: bool) -> None:
    """Build, schedule and evaluate a wide circuit of about --gates gates (foundation targets:
    <= 30 s and <= 3 GB for 50 M gates; >= 100 M gates/s in the clear)."""
    from .compiler import compiler_report

    _emit(compiler_report(gates, lane_words), as_json)


@main.command()
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def ops(as_json: bool) -> None:
    """AND, XOR and AND-depth of every arithmetic op (float32 and integer building blocks)."""
    from .ops import ops_report

    _emit(ops_report(), as_json)


@main.command()
@click.option("--algorithm", type=click.Choice(["lm", "gn"]), default="lm", show_default=True,
              help="Levenberg-Marquardt (damped) or Gauss-Newton.")
@click.option("--mode", type=click.Choice(["sil", "do"]), default="sil", show_default=True,
              help="sil: one iteration per circuit; do: the data-oblivious 20-iteration baseline.")
@click.option("--points", type=click.IntRange(4, 4096), default=6, show_default=True,
              help="Number of point correspondences the circuit takes.")
@click.option("--solve", type=click.Choice(["client", "circuit"]),
              help="client (default for sil): the circuit returns the normal equations and "
                   "the client solves; circuit (forced for do): the paper's in-circuit solve.")
@click.option("--solver", type=click.Choice(["ldlt", "svd"]), default="ldlt", show_default=True,
              help="Linear solver for the 6x6 step inside the circuit (--solve circuit).")
@ARITH
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def circuit(algorithm: str, mode: str, points: int, solve: str | None, solver: str,
            arith: str | None, as_json: bool) -> None:
    """AND/XOR gates, AND-depth, schedule steps and build time of a localization circuit."""
    from .circuit import circuit_report

    try:
        spec = _spec(algorithm, mode, solve, solver, points, arith)
    except ValueError as e:
        raise click.UsageError(str(e)) from None
    _emit(circuit_report(spec), as_json)


@main.command()
@click.option("--scheme", "schemes", type=click.Choice(list(SCHEMES)),
              multiple=True, help="Garbling scheme to measure; repeat for several (default: "
                                  "both, half-gates first). The first one's numbers are the "
                                  "top-level fields; each scheme's are under 'schemes'.")
@click.option("--engine", "engine_names", type=click.Choice(["native", "numpy"]),
              multiple=True, help="Engine to measure; repeat for several (default: the "
                                  "native kernel where it can run, and numpy, in the same "
                                  "run). Each engine's numbers are under 'engines'; the "
                                  "top-level fields are the engine the daemons would serve "
                                  "with ($SNAIL_ENGINE).")
@click.option("--threads", type=click.IntRange(1, 2),
              help="Threads the native kernel cuts wide steps across (default: "
                   "$SNAIL_KERNEL_THREADS, else 1). With 2 the native figures use two "
                   "cores; the report's kernel_threads says so.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def engine(schemes: tuple[str, ...], engine_names: tuple[str, ...], threads: int | None,
           as_json: bool) -> None:
    """Garbling engine: AES rate, garble/evaluate AND gates per second on wide steps,
    per-step overhead on narrow ones, a two-process loopback rate, and the garbler ->
    evaluator bytes per AND gate, per scheme (with both: bytes_ratio, three-halves over
    half-gates) and per engine (the native kernel and numpy)."""
    from snail_common.gc.engine import NativeUnavailable

    from .engine import SCHEMES, engine_report

    try:
        report = engine_report(schemes=tuple(dict.fromkeys(schemes)) or tuple(SCHEMES),
                               engine_names=engine_names or None, threads=threads)
    except NativeUnavailable as exc:
        raise click.BadParameter(f"native: {exc}", param_hint="--engine") from None
    _emit(report, as_json)


@main.command()
@click.option("--algorithm", type=click.Choice(["lm", "gn"]), default="lm", show_default=True,
              help="Levenberg-Marquardt (damped) or Gauss-Newton.")
@click.option("--mode", type=click.Choice(["sil", "do"]), default="sil", show_default=True,
              help="sil: one iteration per circuit; do: the data-oblivious 20-iteration baseline.")
@click.option("--solve", type=click.Choice(["client", "circuit"]),
              help="client (default for sil): the circuit returns the normal equations and "
                   "the client solves; circuit (forced for do): the paper's in-circuit solve.")
@click.option("--solver", type=click.Choice(["ldlt", "svd"]), default="ldlt", show_default=True,
              help="Linear solver for the 6x6 step inside the circuit (--solve circuit).")
@click.option("--points", type=click.IntRange(4, 4096), multiple=True, metavar="N",
              help="Circuit size; repeat for several (default: 6 and 12; 64 and 256 take "
                   "minutes and gigabytes, only when asked).")
@click.option("--repeat", type=click.IntRange(1, 1000), default=5, show_default=True,
              help="Warm runs per circuit, after one first run that may load the circuit.")
@click.option("--garbler", metavar="HOST:PORT",
              help="A running garbler (with --evaluator and --tls-dir); default: start both "
                   "daemons on loopback with throwaway certificates.")
@click.option("--evaluator", metavar="HOST:PORT", help="A running evaluator.")
@click.option("--tls-dir", type=click.Path(exists=True, file_okay=False),
              help="Directory from `snail-client certs` with the client's certificate.")
@click.option("--clients", type=click.IntRange(1, 256), default=1, show_default=True,
              help="Concurrent clients (each with its own connections) invoking the same "
                   "circuit: adds total invocations per second and each client's median.")
@click.option("--lane-window-ms", type=click.FloatRange(0, 1000), default=None,
              help="Embedded daemons only: their --lane-window-ms (batch concurrent "
                   "sessions into lanes; 0: off; default: the daemons' own).")
@click.option("--scheme", type=click.Choice(list(CLIENT_SCHEMES)),
              default=AUTO, show_default=True,
              help="Garbling scheme of every session: three-halves sends 0.77x the table "
                   "bytes but garbles slower, and is never batched into lanes; auto picks "
                   "per session from the garbler's measured rates (the client's default).")
@click.option("--map-points", "map_points", type=click.IntRange(4, 1_000_000), multiple=True,
              metavar="M", help="The map-owner setting's extra cost: for each --points n "
              "and each M (repeat for several), a snail-mapd on loopback holds a random "
              "M-point map containing a random n-point scene and --repeat frames localize "
              "against it; reports per iteration the seconds and AND gates beside the plain "
              "lm-sil-ldlt-nN circuit's (measured in the same run), the selection's AND "
              "gates (0: it is an OT, no circuit), the map owner's OT time per invocation "
              "and selection time per frame (from its session log) and bytes per link. "
              "Embedded daemons only; implies --solve circuit, --algorithm lm, --mode sil.")
@ARITH
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def service(algorithm: str, mode: str, solve: str | None, solver: str,
            arith: str | None, points: tuple[int, ...], repeat: int,
            garbler: str | None, evaluator: str | None, tls_dir: str | None,
            clients: int, lane_window_ms: float | None, scheme: str,
            map_points: tuple[int, ...], as_json: bool) -> None:
    """End to end over TLS: wall time of a secure invocation (first and warm runs), bytes
    per link, and the servers' peak memory. Circuits are compiled on first use. With
    --map-points, also what the map-owner setting adds (a "map_owner" section)."""
    from snail_client.embedded import check_addresses

    from .service import service_report

    if map_points:
        _map_owner_service(points or SERVICE_POINTS, map_points, repeat, algorithm, mode,
                           solve, solver, garbler, clients, lane_window_ms, scheme, as_json)
        return
    try:
        check_addresses(garbler, evaluator, tls_dir)
        specs = [_spec(algorithm, mode, solve, solver, n, arith)
                 for n in points or SERVICE_POINTS]
    except ValueError as e:
        raise click.UsageError(str(e)) from None
    if lane_window_ms is not None and garbler:
        raise click.UsageError("--lane-window-ms sets the embedded daemons; start "
                               "remote ones with it instead")
    flags = click.get_current_context().find_object(dict) or {}

    def done(name: str, row: dict) -> None:
        if flags.get("verbose"):
            click.echo(f"snail-bench: {name}: median {row['median_s']:.3f} s, first "
                       f"{row['first_s']:.3f} s", err=True)

    _print_service(lambda: service_report(specs, repeat, garbler, evaluator, tls_dir, clients,
                                          lane_window_ms, flags.get("quiet", False), done,
                                          scheme),
                   as_json, _show_service)


def _print_service(measure: Callable[[], dict], as_json: bool,
                   show: Callable[[dict], None]) -> None:
    """The end of ``service``, with or without --map-points: ``measure``'s report as one
    JSON object or as ``show`` prints it; exit 1 if the service fails."""
    from snail_client.links import ServiceError

    try:
        report = measure()
    except ServiceError as e:
        click.echo(f"snail-bench: {e}", err=True)
        sys.exit(1)
    if as_json:
        click.echo(json.dumps(report))
    else:
        show(report)


def _show_service(report: dict) -> None:
    for name, row in report["service"].items():
        mb = row["traffic"]["garbler_to_evaluator"] / 1e6
        rss = "  ".join(f"{role} {v} MB" for role, v in row.get("peak_rss_mb", {}).items())
        click.echo(f"{name:>20}: median {row['median_s']:.3f} s (min {row['min_s']:.3f}, "
                   f"max {row['max_s']:.3f}, first {row['first_s']:.3f})  {mb:.1f} MB "
                   f"garbler->evaluator  {row['and']:,} AND  peak RSS {rss or 'n/a'}")
        if "clients" in row:
            worst = max(row["client_median_s"])
            click.echo(f"{'':>20}  {row['clients']} clients: "
                       f"{row['throughput_inv_per_s']:.1f} invocations/s in total, "
                       f"slowest client's median {worst:.3f} s")


def _map_owner_service(points: tuple[int, ...], map_points: tuple[int, ...], repeat: int,
                       algorithm: str, mode: str, solve: str | None, solver: str,
                       garbler: str | None, clients: int, lane_window_ms: float | None,
                       scheme: str, as_json: bool) -> None:
    """``service --map-points``: the plain and map-owner circuits side by side."""
    from .mapowner import map_owner_report

    if garbler or clients > 1 or algorithm != "lm" or mode != "sil" or solve == "client" \
            or solver != "ldlt":
        raise click.UsageError("--map-points measures embedded daemons, one client, the "
                               "map-owner circuit lm-sil-ldlt (no --garbler, --clients, "
                               "--algorithm gn, --mode do, --solve client or --solver svd)")
    if any(m < n for m in map_points for n in points):
        raise click.UsageError("--map-points: every map must hold the scene's --points")
    lanes = () if lane_window_ms is None else ("--lane-window-ms", str(lane_window_ms))
    _print_service(lambda: map_owner_report(points, map_points, repeat, scheme, lanes),
                   as_json, _show_map_owner)


def _show_map_owner(report: dict) -> None:
    for name, by_m in report["map_owner"].items():
        for m, row in by_m.items():
            pad, sel = row["pad_ot"], row["selection"]
            click.echo(f"{name:>20} M={m:>7}: median {row['median_s']:.3f} s/iteration "
                       f"(first setting, {row['plain_circuit']}: {row['plain_frame_median_s']:.3f} "
                       f"s)  "
                       f"{row['and']:,} AND (plain {row['plain_and']:,}; selection 0)  "
                       f"pad OT {pad['map_owner_s']} s, {pad['mapowner_to_garbler']:,} B "
                       f"up / {pad['garbler_to_mapowner']:,} B down per iteration  "
                       f"selection {sel['map_owner_s']} s, {sel['bytes_to_device']:,} B "
                       f"per frame  pose == cleartext: {row['pose_equals_cleartext']}")


@main.command()
@click.option("--clients", type=click.IntRange(1, 256), default=16, show_default=True,
              help="Client processes, each with its own certificate and connections.")
@click.option("--minutes", type=click.FloatRange(0.05, 10_000), default=10.0,
              show_default=True, help="How long clients start new frames (fractions "
                                      "allowed: 0.25 is 15 s).")
@click.option("--points", type=click.IntRange(4, 4096), multiple=True, metavar="N",
              help="Scene sizes the clients pick from at random; repeat for several "
                   "(default: 6 and 12).")
@click.option("--algorithm", "algorithms", type=click.Choice(["lm", "gn"]), multiple=True,
              help="Algorithms the clients pick from at random (default: lm and gn).")
@click.option("--min-invocations", type=click.IntRange(0, 1000), default=20,
              show_default=True, help="Secure runs per frame, padding included (the "
                                      "privacy policy's floor).")
@click.option("--sample-seconds", type=click.FloatRange(0.1, 60), default=2.0,
              show_default=True, help="How often the daemons' RSS and open fds are read.")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path),
              help="Write soak.json, soak.png (curves over time; needs the bench "
                   "extra) and the daemons' logs (garbler.log, evaluator.log) into DIR.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def soak(clients: int, minutes: float, points: tuple[int, ...], algorithms: tuple[str, ...],
         min_invocations: int, sample_seconds: float, out: Path | None,
         as_json: bool) -> None:
    """A fleet of client processes localizing random scenes (mixed sizes and algorithms)
    against one daemon pair on loopback for --minutes; every frame's pose is checked bit
    for bit against the cleartext backend on the same scene. Reports invocations, failures
    by kind, latency percentiles (overall and per minute), and each daemon's RSS, open
    fds, sessions and tables buffered ahead per minute (largest sample), whether both
    daemons are idle once the clients left, and their logs' session outcomes. Verdict:
    flat when, for each daemon, the last minute's RSS and fds are within 10 % of the
    second minute's (null under 3 minutes).
    Exit 1 on any wrong result or any failure other than busy (a server at its session
    limit beyond the client's busy wait), else 0. Clients finish the frame under way at
    the end; that wind-down is reported apart."""
    from .soak import Plan, run_soak

    plan = Plan(clients, minutes, points or SERVICE_POINTS, algorithms or ("lm", "gn"),
                min_invocations, sample_seconds)
    if out is not None:
        try:
            from .soak_plot import plot_soak
        except ImportError as e:
            click.echo(f"snail-bench: --out needs the bench extra ({e}): "
                       "pip install 'snail[bench]'", err=True)
            sys.exit(2)
    flags = click.get_current_context().find_object(dict) or {}
    from snail_client.links import ServiceError

    try:
        report = run_soak(plan, flags.get("quiet", False), out)
    except ServiceError as e:
        click.echo(f"snail-bench: {e}", err=True)
        sys.exit(1)
    except KeyboardInterrupt:
        click.echo("snail-bench: interrupted", err=True)
        sys.exit(130)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "soak.json").write_text(json.dumps(report, indent=1) + "\n")
        plot_soak(report["soak"], out / "soak.png")
    body = report["soak"]
    if as_json:
        click.echo(json.dumps(report))
    else:
        lat = body["latency_s"]
        click.echo(f"{body['clients']} clients, {body['minutes'] * 60:.0f} s: "
                   f"{body['invocations']} invocations (and "
                   f"{body['wind_down']['invocations']} in the {body['wind_down']['seconds']:.0f}"
                   f" s wind-down), {body['frames']} frames checked, {body['wrong']} wrong, "
                   f"failures {body['failures'] or 'none'}")
        click.echo(f"latency p50 {lat['p50']} s  p95 {lat['p95']} s  p99 {lat['p99']} s")
        click.echo(f"invocations per minute {body['invocations_per_minute']}")
        for what in ("rss_mb", "fds", "sessions", "queued_mb"):
            for role, series in body[what].items():
                click.echo(f"{what} {role}: {series}")
        click.echo(f"flat: {body['flat']}  ({body['flat_by_series']})")
        after = body["after_clients_left"]
        click.echo(f"after the clients left: {'idle' if after['idle'] else 'NOT idle'} "
                   f"within {after['seconds']} s  garbler {after['garbler']}  "
                   f"evaluator {after['evaluator']}")
        for role, log in body["daemon_logs"].items():
            click.echo(f"{role} log: sessions {log['sessions']}  warnings "
                       f"{log['warnings'] or 'none'}")
    if not body["ok"]:
        sys.exit(1)


@main.command()
@click.option("--scenes", type=click.IntRange(1, 1_000_000), default=1000, show_default=True,
              help="Scenes per algorithm.")
@click.option("--kind", type=click.Choice(["random", "one-tag", "plane-tags", "far-few"]),
              default="random", show_default=True,
              help="random: n log-uniform in 4..256, 0.5 px noise, initial pose 2-10 "
                   "degrees and 5-20 % off, --planar-share of them on one plane; one-tag: "
                   "the 4 corners of a 6.5 cm tag, 10-200 px a side in a 640x480 image at "
                   "f 330-340 px, 0-70 degrees oblique, 0.1-0.5 px noise, started 5 "
                   "degrees and 10 % off IPPE's pose; plane-tags: 2-6 such tags on one "
                   "plane; far-few: 6-12 points 10-50 m away with 2-10 % depth spread.")
@click.option("--algorithm", "algorithms", type=click.Choice(["lm", "gn"]), multiple=True,
              help="Algorithm to sweep; repeat for both (default: lm and gn).")
@click.option("--solve", type=click.Choice(["client", "circuit"]), default="client",
              show_default=True, help="Which circuit family's mirror: the normal equations "
                                      "solved by the client, or the in-circuit solve.")
@ARITH
@click.option("--planar-share", type=click.FloatRange(0, 1), default=0.25, show_default=True,
              help="Share of scenes whose points lie on one tilted plane (a tag, a wall).")
@click.option("--seed", type=int, default=1, show_default=True,
              help="Sweep seed: scene k of a seed is the same on every run.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@click.pass_context
def accuracy(ctx: click.Context, scenes: int, kind: str, algorithms: tuple[str, ...],
             solve: str, arith: str | None, planar_share: float, seed: int,
             as_json: bool) -> None:
    """How often the client's LM/GN loop, on the circuits' bit-exact float32 mirror, ends
    within max(0.01 px, 0.5 %) of the reprojection RMS of OpenCV's iterative solvePnP, and
    of the same loop in float64, from the same initial pose; lists every scene that does
    not. Exit 1 below 99.9 % (LM) or 99 % (GN) against OpenCV on random scenes; on the
    other kinds, against float64, below all (LM) or 99.5 % (GN; 99 % with --solve
    circuit)."""
    from snail_client.progress import bar

    from .accuracy import sweep

    algorithms = algorithms or ("lm", "gn")
    report, short = {}, []
    quiet = bool(ctx.obj and ctx.obj.get("quiet"))
    with bar(scenes * len(algorithms), "accuracy", quiet, "scene") as progress:
        for algorithm in algorithms:
            row = sweep(scenes, algorithm, seed, planar_share, solve, arith,
                        lambda: progress.update(1), kind)
            report[algorithm] = row
            rate, target = ((row["pass_rate"], ACCURACY_TARGETS[algorithm]) if kind == "random"
                            else (row["pass_rate_float64"], HARD_TARGETS[algorithm, solve]))
            if rate < target:
                short.append(algorithm)
    if as_json:
        click.echo(json.dumps({"accuracy": report}))
    for algorithm, row in ({} if as_json else report).items():
        kinds = ", ".join(f"{k} {v['passed']}/{v['scenes']}"
                          for k, v in row["passed_by_kind"].items())
        click.echo(f"{algorithm} ({kind}, {row['solve']} solve): {row['passed']}/"
                   f"{row['scenes']} within OpenCV's RMS + max(0.01 px, 0.5 %) ({kinds}), "
                   f"{row['passed_float64']}/{row['scenes']} within float64's (float64: "
                   f"{row['float64']['passed']} within OpenCV's, iterations mean "
                   f"{row['float64']['iterations']['mean']:g}, max "
                   f"{row['float64']['iterations']['max']}); iterations mean "
                   f"{row['iterations']['mean']:g}, max {row['iterations']['max']}; "
                   f"invocations mean {row['invocations']['mean']:g}, max "
                   f"{row['invocations']['max']}; not converged: "
                   f"{len(row['not_converged'])} {row['not_converged'] or ''}".rstrip())
        for f in row["failures"]:
            note = "" if f["converged"] else " (not converged)"
            click.echo(f"  scene {f['scene']}: n={f['n']}{' planar' if f['planar'] else ''}"
                       f", {f['rms_px']} px vs OpenCV {f['rms_opencv_px']} px, float64 "
                       f"{f['rms_float64_px']} px after {f['iterations']} iterations "
                       f"(float64 {f['float64_iterations']}){note}")
    if short:
        sys.exit(1)


@main.command("fuzz")
@click.option("--target", "targets", multiple=True, metavar="NAME",
              help="A parser to fuzz (repeatable; default: all of them: frames, message, "
                   "problem, sequence, camera, tagmap, colmap_bin, colmap_txt, revoked, "
                   "certificates, map, frame).")
@click.option("--runs", type=click.IntRange(1), default=1_000_000, show_default=True,
              help="Inputs per target.")
@click.option("--seconds", type=click.IntRange(1), default=3600, show_default=True,
              help="Time limit per target.")
@click.option("--corpus", type=click.Path(file_okay=False, path_type=Path),
              help="Keep each target's corpus and findings in DIR/TARGET (default: a "
                   "temporary folder).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def fuzz_cmd(targets: tuple[str, ...], runs: int, seconds: int, corpus: Path | None,
             as_json: bool) -> None:
    """Coverage-guided fuzzing (atheris) of every parser of untrusted bytes, each from
    valid seeds, with a 5 s limit per input and 1 GiB of memory: exit 1 on any crash,
    hang or runaway allocation, with the input kept. Needs the fuzz extra."""
    try:
        import atheris  # noqa: F401
    except ImportError:
        click.echo("snail-bench: fuzz needs atheris: pip install 'snail[fuzz]'", err=True)
        sys.exit(2)
    from .fuzz import fuzz
    from .fuzz_targets import TARGETS

    unknown = sorted(set(targets) - set(TARGETS))
    if unknown:
        raise click.UsageError(f"--target: unknown {', '.join(unknown)}; choose from "
                               f"{', '.join(TARGETS)}")
    report = {}
    for name in targets or TARGETS:
        report[name] = fuzz(name, runs, seconds, corpus / name if corpus else None)
        if not as_json:
            row = report[name]
            click.echo(f"{name:>12}: {row['runs']} inputs in {row['seconds']} s, "
                       f"{'ok' if row['ok'] else 'FOUND ' + ', '.join(row['findings'])}")
    if as_json:
        click.echo(json.dumps({"fuzz": report}))
    if not all(row["ok"] for row in report.values()):
        sys.exit(1)


if __name__ == "__main__":
    sys.exit(main())
