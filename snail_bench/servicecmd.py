"""``snail-bench service``: a secure invocation end to end over TLS, and with --map-points
what the map-owner setting adds. The measuring lives in ``service.py`` and ``mapowner.py``;
here are the flags, their checks and what a person reads."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable

import click

from snail_common.net.linkrates import AUTO, CLIENT_SCHEMES

from .choices import ARITH, SERVICE_POINTS, TABLE_LINK, circuit_options
from .choices import spec as _spec


@click.command()
@circuit_options
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
@TABLE_LINK
@ARITH
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def service(algorithm: str, mode: str, solve: str | None, solver: str,
            arith: str | None, points: tuple[int, ...], repeat: int,
            garbler: str | None, evaluator: str | None, tls_dir: str | None,
            clients: int, lane_window_ms: float | None, scheme: str,
            map_points: tuple[int, ...], table_link: str | None, as_json: bool) -> None:
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
    if table_link is not None and garbler:
        raise click.UsageError("--table-link sets the embedded daemons; start remote ones "
                               "with it instead")
    flags = click.get_current_context().find_object(dict) or {}

    def done(name: str, row: dict) -> None:
        if flags.get("verbose"):
            click.echo(f"snail-bench: {name}: median {row['median_s']:.3f} s, first "
                       f"{row['first_s']:.3f} s", err=True)

    _print_service(lambda: service_report(specs, repeat, garbler, evaluator, tls_dir, clients,
                                          lane_window_ms, flags.get("quiet", False), done,
                                          scheme, table_link),
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
