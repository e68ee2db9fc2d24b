"""Command-line plumbing shared by ``snail-garbler`` and ``snail-evaluator``."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, NoReturn

import click

from snail_common import failpoints
from snail_common.circuit import cache, registry
from snail_common.gc.engine import ENGINE_ENV, engine_status
from snail_common.gc.native.build import NativeUnavailable

from .conn import parse_addr
from .logs import announce
from .messages import TABLE_LINKS
from .service import Options

LOG_LEVELS = ("debug", "info", "warning", "error")


def address(ctx: click.Context, param: click.Parameter, value: str | None):
    """click callback: HOST:PORT -> (host, port)."""
    if value is None:
        return None
    try:
        return parse_addr(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


def addresses(ctx: click.Context, param: click.Parameter,
              values: tuple[str, ...]) -> tuple[tuple[str, int], ...]:
    """click callback for a repeatable HOST:PORT option."""
    return tuple(address(ctx, param, value) for value in values)


def map_owner_option(role: str, dials_to: str, refused: str, how: str = "",
                     names: str = "") -> Callable[..., Any]:
    """``--map-owner HOST:PORT`` (repeatable, as ``map_owners``): the map owners a server
    may dial ``dials_to`` do something, and no others (a client naming another is
    refused: no client can make a server connect wherever it likes). ``how`` and
    ``names`` add the role's own sentences before and after that rule."""
    text = (f"A map owner (snail-mapd) this {role} may dial {dials_to} (repeatable). "
            f"{how + ' ' if how else ''}Clients name the map owner; the {role} dials only "
            f"the ones allowed here, so that no client can make it connect wherever it "
            f"likes. Default: none, and {refused} are refused.{' ' + names if names else ''}")
    return click.option("--map-owner", "map_owners", multiple=True, callback=addresses,
                        metavar="HOST:PORT", help=text)


def daemon_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    """The flags every daemon takes (besides its addresses)."""
    defaults = Options()
    for option in reversed([
        click.option("--tls-dir", required=True,
                     type=click.Path(exists=True, file_okay=False),
                     help="Directory made by 'snail-client certs' (CA and role certs)."),
        click.version_option(package_name="snail"),
        click.option("--log-level", type=click.Choice(LOG_LEVELS), default="info",
                     show_default=True, help="JSON log lines on stderr from this level."),
        click.option("-v", "--verbose", is_flag=True, help="Same as --log-level debug."),
        click.option("-q", "--quiet", is_flag=True, help="Same as --log-level warning."),
        click.option("--max-sessions", type=click.IntRange(1, 100_000),
                     default=defaults.max_sessions, show_default=True,
                     help="Concurrent sessions, reservations (garbled ahead) included. "
                          "At the limit a live session takes a reservation's place; it is "
                          "refused as busy only when none is left."),
        click.option("--session-timeout", type=click.FloatRange(0.1, 3600),
                     default=defaults.session_timeout, show_default=True,
                     help="Seconds a session may wait for its peer's next message."),
        click.option("--workers", type=click.IntRange(1, 256), default=defaults.workers,
                     show_default=True, help="Threads for garbling/evaluation."),
        click.option("--max-and-gates", type=click.IntRange(1, 10**10),
                     default=defaults.max_and_gates, show_default=True,
                     help="Largest circuit (in AND gates) this daemon compiles or loads; "
                          "bigger ones are refused as too_large. Memory peaks at about "
                          "200 bytes per AND gate of the largest circuit."),
        click.option("--ahead-mb", type=click.IntRange(0, 1 << 20),
                     default=defaults.ahead_bytes >> 20, show_default=True,
                     help="Evaluator: MiB of garbled tables held for sessions garbled "
                          "ahead of their client's labels; beyond it streams wait."),
        click.option("--ahead-mb-per-peer", type=click.IntRange(0, 1 << 20),
                     default=defaults.ahead_bytes_per_peer >> 20, show_default=True,
                     help="Evaluator: the share of --ahead-mb one client certificate name "
                          "may fill."),
        click.option("--lane-window-ms", type=click.FloatRange(0, 1000),
                     default=defaults.lane_window_ms, show_default=True,
                     help="Sessions of the same circuit starting within this many ms "
                          "(garbler: requests; evaluator: client labels) run together as "
                          "lanes of one pass: more throughput for a fleet of clients. A "
                          "session waits for the window only while another run of its "
                          "circuit is under way, so a lone client never does; 0: off."),
        click.option("--max-lanes", type=click.IntRange(1, 256), default=defaults.max_lanes,
                     show_default=True, help="Most sessions in one lane batch."),
        click.option("--idle-timeout", type=click.FloatRange(0.1, 86400),
                     default=defaults.idle_timeout, show_default=True,
                     help="Seconds a connection may stay silent with no session under way "
                          "before it is closed. A frame, once begun, must arrive within "
                          "--session-timeout."),
        click.option("--handshake-timeout", type=click.FloatRange(0.1, 3600),
                     default=defaults.handshake_timeout, show_default=True,
                     help="Seconds a new connection has to finish its TLS handshake and "
                          "say hello; slower ones are closed (a peer that connects and "
                          "stalls holds nothing for longer)."),
        click.option("--max-sessions-per-peer", type=click.IntRange(1, 100_000),
                     default=defaults.max_sessions_per_peer, show_default=True,
                     help="Concurrent sessions one client certificate name may hold "
                          "(clients sharing a certificate share it); more are busy."),
        click.option("--max-ahead-per-peer", type=click.IntRange(0, 100_000),
                     default=defaults.max_ahead_per_peer, show_default=True,
                     help="Of a client certificate name's sessions, how many may be "
                          "reservations (garbled ahead of need). A live session that "
                          "meets a full daemon takes a reservation's place (the client "
                          "holding the most loses its newest, as 'evicted'); more "
                          "reservations than this are refused as busy."),
        click.option("--max-connections-per-peer", type=click.IntRange(1, 100_000),
                     default=defaults.max_connections_per_peer, show_default=True,
                     help="Open connections one client certificate name may hold."),
        click.option("--metrics", callback=address, metavar="HOST:PORT",
                     help="Serve /metrics (Prometheus text) and /health (JSON) over HTTPS "
                          "with this daemon's certificate (no client certificate needed: "
                          "counts only). Default: off."),
        click.option("--cache-dir", type=click.Path(file_okay=False, path_type=Path),
                     help="Compiled circuits on disk (default: $SNAIL_CACHE_DIR, else "
                          "~/.cache/snail)."),
        click.option("--cache-max-gb", type=click.FloatRange(0.001, 1e6),
                     default=cache.DEFAULT_MAX_BYTES / 2**30, show_default=True,
                     help="Disk cache bound: after a new circuit is stored, the least "
                          "recently used others are removed until the rest fit."),
        click.option("--memory-cache-gb", type=click.FloatRange(0.001, 1e6),
                     default=registry.DEFAULT_MEMORY_BYTES / 2**30, show_default=True,
                     help="Compiled circuits kept in memory, in GiB of their arrays (the "
                          "most recent one always stays)."),
        click.option("--table-link", type=click.Choice(TABLE_LINKS),
                     default=defaults.table_link, show_default=True,
                     help="How the garbler's tables travel to the evaluator; the same on "
                          "both servers. aead: a second connection to the evaluator's port "
                          "beside the TLS one, each ~1 MiB frame sealed with AES-256-GCM "
                          "under a key fresh per link (handed over the mutual-TLS one). "
                          "digest: that second connection unencrypted, integrity from the "
                          "garbler's signed digest of the tables (for servers on a private "
                          "link). tls: inside the TLS connection (one port; the slowest). "
                          "docs/security.md weighs them."),
        click.option("--grace", type=click.FloatRange(0, 3600), default=defaults.grace,
                     show_default=True,
                     help="Seconds SIGTERM waits for running sessions to finish."),
    ]):
        fn = option(fn)
    return fn


def options_from(kwargs: dict[str, Any]) -> Options:
    return Options(max_sessions=kwargs["max_sessions"],
                   session_timeout=kwargs["session_timeout"], grace=kwargs["grace"],
                   workers=kwargs["workers"], max_and_gates=kwargs["max_and_gates"],
                   ahead_bytes=kwargs["ahead_mb"] << 20,
                   ahead_bytes_per_peer=kwargs["ahead_mb_per_peer"] << 20,
                   lane_window_ms=kwargs["lane_window_ms"], max_lanes=kwargs["max_lanes"],
                   idle_timeout=kwargs["idle_timeout"],
                   handshake_timeout=kwargs["handshake_timeout"],
                   max_sessions_per_peer=kwargs["max_sessions_per_peer"],
                   max_ahead_per_peer=kwargs["max_ahead_per_peer"],
                   max_connections_per_peer=kwargs["max_connections_per_peer"],
                   table_link=kwargs["table_link"],
                   tls_dir=kwargs["tls_dir"], metrics=kwargs["metrics"])


def configure_caches(kwargs: dict[str, Any]) -> None:
    """Apply --cache-dir, --cache-max-gb and --memory-cache-gb to this process."""
    cache.configure(kwargs["cache_dir"], int(kwargs["cache_max_gb"] * 2**30))
    registry.configure(int(kwargs["memory_cache_gb"] * 2**30))


def choose_engine(prog: str) -> dict[str, str]:
    """The garbling engine this daemon serves with ($SNAIL_ENGINE, gc/engine.py), built
    now (the native kernel compiles on first use), and its threads ($SNAIL_KERNEL_THREADS);
    exit 2 naming the setting when it asks for an engine that cannot run or is malformed."""
    try:
        return engine_status()
    except NativeUnavailable as exc:
        fail(2, f"${ENGINE_ENV}: {exc}", prog)
    except ValueError as exc:  # it names its variable: $SNAIL_ENGINE or $SNAIL_KERNEL_THREADS
        fail(2, f"${exc}", prog)


def arm_failpoints(role: str, prog: str, logger: logging.Logger) -> None:
    """Arm this daemon's failpoints from $SNAIL_FAILPOINTS (snail_common/failpoints.py),
    once, at start: a warning line lists them; exit 2 naming the setting when it is
    malformed or names an unknown point."""
    try:
        armed = failpoints.configure(role)
    except failpoints.FailpointError as exc:
        fail(2, str(exc), prog)
    if armed:
        announce(logger, "failpoints", logging.WARNING, armed=armed,
                 reason=f"${failpoints.ENV}: this {role} misbehaves on purpose")


def fail(code: int, message: str, prog: str | None = None) -> NoReturn:
    """One line on stderr, named after the command, and exit ``code`` (2: usage/input)."""
    click.echo(f"{prog or Path(sys.argv[0]).name}: {message}", err=True)
    sys.exit(code)


def log_level_of(log_level: str, kwargs: dict[str, Any]) -> str:
    """--log-level, unless -v or -q says otherwise."""
    if kwargs.get("verbose") and kwargs.get("quiet"):
        fail(2, "-v and -q: choose one")
    return "debug" if kwargs.get("verbose") else "warning" if kwargs.get("quiet") else log_level
