"""snail-mapd: the map owner's daemon (the map-owner setting, docs/map-owner.md)."""

from __future__ import annotations

from pathlib import Path

import click

from snail_common.loc.mapfile import load_map
from snail_common.loc.owner import owner_values
from snail_common.loc.problem import ProblemError
from snail_common.net import tls
from snail_common.net.cli import LOG_LEVELS, address, addresses, fail, log_level_of
from snail_common.net.conn import format_addr
from snail_common.net.listener import run_daemon
from snail_common.net.logs import setup
from snail_common.net.options import Options
from snail_common.net.parent import exit_with_parent

from .daemon import MAX_FRAMES, MapOwnerDaemon

_DEFAULTS = Options()


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--listen", required=True, callback=address, metavar="HOST:PORT",
              help="Address to accept devices and the garbler on (port 0: any free port).")
@click.option("--map", "map_path", required=True,
              type=click.Path(dir_okay=False, path_type=Path), metavar="MAP.json",
              help="The map (snail-map/1: point ids and 3D coordinates). It never leaves "
                   "this process in the clear: devices get their points under one-time "
                   "pads, the circuit gets the pads by oblivious transfer.")
@click.option("--evaluator", "evaluators", multiple=True, callback=addresses,
              metavar="NAME:PORT",
              help="An evaluator this map owner may send the labels of its wires to "
                   "(repeatable; a name may resolve to several replicas). The garbler "
                   "names the replica of each session; any other is refused as forbidden. "
                   "Default: none, and every invocation is refused.")
@click.option("--tls-dir", required=True, type=click.Path(exists=True, file_okay=False),
              help="Directory made by 'snail-client certs' (CA and the mapowner "
                   "certificate).")
@click.option("--max-frames", type=click.IntRange(1, 1_000_000), default=MAX_FRAMES,
              show_default=True,
              help="Selections (frames) whose pads are kept for their invocations; the "
                   "oldest is forgotten first.")
@click.option("--max-sessions", type=click.IntRange(1, 100_000),
              default=_DEFAULTS.max_sessions, show_default=True,
              help="Concurrent selections and invocations before new ones are busy.")
@click.option("--session-timeout", type=click.FloatRange(0.1, 3600),
              default=_DEFAULTS.session_timeout, show_default=True,
              help="Seconds an invocation waits for the garbler's OT answer.")
@click.option("--idle-timeout", type=click.FloatRange(0.1, 86400),
              default=_DEFAULTS.idle_timeout, show_default=True,
              help="Seconds a silent connection stays open.")
@click.option("--handshake-timeout", type=click.FloatRange(0.1, 3600),
              default=_DEFAULTS.handshake_timeout, show_default=True,
              help="Seconds a new connection has for its TLS handshake and hello.")
@click.option("--workers", type=click.IntRange(1, 256), default=_DEFAULTS.workers,
              show_default=True, help="Threads for the selection tables and OTs.")
@click.option("--grace", type=click.FloatRange(0, 3600), default=_DEFAULTS.grace,
              show_default=True, help="Seconds SIGTERM waits for running sessions.")
@click.option("--log-level", type=click.Choice(LOG_LEVELS), default="info",
              show_default=True, help="JSON log lines on stderr from this level.")
@click.option("-v", "--verbose", is_flag=True, help="Same as --log-level debug.")
@click.option("-q", "--quiet", is_flag=True, help="Same as --log-level warning.")
@click.version_option(package_name="snail")
def main(listen: tuple[str, int], map_path: Path, tls_dir: str, max_frames: int,
         evaluators: tuple[tuple[str, int], ...], log_level: str, **kwargs) -> None:
    """Map-owner daemon: serves devices' oblivious selections of map points (each gets its
    points under pads only this daemon holds) and inputs the pads into every iteration
    circuit by oblivious transfer with the garbler (see snail_mapd.daemon)."""
    exit_with_parent()
    logger = setup("mapowner", log_level_of(log_level, kwargs))
    try:
        published, values = owner_values(load_map(map_path))
    except ProblemError as exc:
        fail(2, f"--map {map_path}: {exc}", "snail-mapd")
    options = Options(max_sessions=kwargs["max_sessions"],
                      session_timeout=kwargs["session_timeout"],
                      idle_timeout=kwargs["idle_timeout"],
                      handshake_timeout=kwargs["handshake_timeout"],
                      workers=kwargs["workers"], grace=kwargs["grace"], tls_dir=tls_dir)
    try:
        server_ctx = tls.server_context(tls_dir, "mapowner")
        client_ctx = tls.client_context(tls_dir, "mapowner")
        daemon = MapOwnerDaemon(options, logger, published, values, client_ctx, max_frames,
                                evaluators)
    except (OSError, ValueError) as exc:
        fail(2, f"--tls-dir: {exc}", "snail-mapd")
    try:
        interrupted = run_daemon(daemon, listen, server_ctx)
    except OSError as exc:
        raise click.ClickException(f"--listen {format_addr(*listen)}: {exc}") from None
    if interrupted:
        fail(130, "interrupted: running sessions ended with an error to their peers",
             "snail-mapd")
