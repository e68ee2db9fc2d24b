"""What both daemons share: the TLS listener, connection opening, compiled circuits, the
worker pool, session bookkeeping with per-peer quotas, revocation, health and metrics,
structured logs and graceful shutdown.

CPU work (compiling, garbling, evaluating) runs in a thread pool: numpy and AES release
the GIL, and the event loop stays free for other sessions, TLS and health requests.
SIGTERM/SIGINT stop accepting, let running sessions finish for up to ``grace`` seconds,
then say ``bye`` to every peer and exit. SIGHUP rereads ``revoked.txt`` and drops the
connections of peers it now lists.

Every session ends with one JSON log line ``{"event": "session", "peer", "circuit",
"and", "bytes_in", "bytes_out", "seconds", "outcome"}`` (outcome ``ok`` or an error code),
and the same numbers feed the counters of ``health`` and ``--metrics``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import ssl
import sys
import time
from collections import Counter
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from snail_common.circuit import registry
from snail_common.circuit.ir import Circuit
from snail_common.circuit.plan import plan_for
from snail_common.circuit.schedule import Schedule

from . import messages
from .conn import SOFTWARE, Connection, accept, prefer_bursts
from .errors import (
    BUSY,
    CIRCUIT_MISMATCH,
    INTERNAL,
    REVOKED,
    TIMEOUT,
    TOO_LARGE,
    UNEXPECTED,
    UNKNOWN_CIRCUIT,
    ConnectionClosed,
    ProtocolError,
    RemoteError,
)
from .frames import MAX_FRAME, BodyPool
from .heap import HeapTrimmer
from .logs import announce, event
from .metrics import OK, Metrics
from .scrape import scrape_context, serve_scrapes
from .tls import TLSFileError, read_revoked

T = TypeVar("T")
# workers hold the GIL between numpy calls; a short switch interval lets the event loop
# (TLS, other sessions) in sooner than the default 5 ms
SWITCH_INTERVAL = 5e-4


@dataclass
class Options:
    """Daemon settings shared by garbler and evaluator (CLI flags of the same names)."""

    max_sessions: int = 64
    session_timeout: float = 30.0  # longest wait for a peer's next message mid-session
    handshake_timeout: float = 10.0
    grace: float = 10.0  # how long shutdown waits for running sessions
    workers: int = max(2, os.cpu_count() or 2)
    # largest circuit compiled or loaded: a daemon's memory peaks at ~200 bytes per AND
    # gate of it (n=256 SIL-LM: 15.2 M AND, 3.0 GB; 20-iteration DO at n=6: 12.6 M, 2.2 GB)
    max_and_gates: int = 40_000_000
    # garbled tables an evaluator holds for sessions whose client has not sent its labels
    # yet (garble-ahead); beyond this the garbler's streams wait
    ahead_bytes: int = 256 << 20
    ahead_bytes_per_peer: int = 128 << 20  # one client certificate name's share of it
    # sessions of one circuit starting within this window run as lanes of one pass
    # (garbler: requests; evaluator: client labels; 0: off), at most max_lanes at once; a
    # session waits for the window only while another run of its circuit is under way
    lane_window_ms: float = 10.0
    max_lanes: int = 16
    # a connection with no session and no message for this long is closed
    idle_timeout: float = 300.0
    # fairness between clients, by certificate name (clients sharing a certificate share
    # these); the garbler's links to the evaluator are not counted
    max_sessions_per_peer: int = 32
    max_connections_per_peer: int = 64
    tls_dir: str | None = None  # where revoked.txt is read from (at start and on SIGHUP)
    metrics: tuple[str, int] | None = None  # HTTPS endpoint for /metrics and /health


BODIES_IDLE_S = 1.0  # recycled table frames are dropped once the daemon is idle this long


class Daemon:
    """Base of the daemons; a subclass serves each certificate role of ``allowed`` in a
    method ``_serve_<role>(conn)`` that returns once the connection is done (or
    overrides ``serve``)."""

    role = ""
    allowed: tuple[str, ...] = ()  # certificate roles that may connect
    gone_event = "peer_gone"  # the log line of a peer lost mid-connection

    def __init__(self, options: Options, logger: logging.Logger) -> None:
        self.options = options
        self.log = logger
        self.pool = ThreadPoolExecutor(options.workers, thread_name_prefix=self.role)
        self.connections: set[Connection] = set()
        # received table frames kept for the next ones while sessions run, at most the
        # garbled-ahead budget (what buffered frames may hold anyway)
        self.bodies = BodyPool(options.ahead_bytes)
        self._tasks: set[asyncio.Task] = set()
        self._planned: dict[str, int] = {}  # circuit id -> id() of the planned schedule
        self.metrics = Metrics(self.role, lambda: len(self.connections))
        self.counters = self.metrics.gauges  # active, streaming, queued_bytes
        self._peer_sessions: Counter[str] = Counter()
        self.revoked = read_revoked(options.tls_dir) if options.tls_dir else frozenset()
        self.started = time.monotonic()
        self.heap = HeapTrimmer()
        self.stopping = asyncio.Event()
        self.interrupted = False

    # ---- subclass interface ------------------------------------------------------------
    async def shutdown_extra(self) -> None:
        """Close what the subclass owns (e.g. pooled outgoing connections)."""

    # ---- helpers for subclasses ----------------------------------------------------------
    def capabilities(self) -> dict[str, Any]:
        return messages.make("capabilities", role=self.role, software=SOFTWARE,
                             max_frame=MAX_FRAME, families=list(registry.families()),
                             max_sessions=self.options.max_sessions,
                             max_and_gates=self.options.max_and_gates)

    def health(self) -> dict[str, Any]:
        return messages.make("health", role=self.role, sessions=self.metrics.health(),
                             uptime_s=round(time.monotonic() - self.started, 3))

    def prometheus(self) -> str:
        return self.metrics.prometheus()

    def submit(self, fn: Callable[..., T], *args: Any) -> asyncio.Future[T]:
        """Start CPU work in the pool now."""
        return asyncio.get_running_loop().run_in_executor(self.pool, fn, *args)

    async def work(self, fn: Callable[..., T], *args: Any) -> T:
        """Run CPU work in the pool and wait for it."""
        return await self.submit(fn, *args)

    async def circuit(self, circuit_id: str, content_hash: str) -> tuple[Circuit, Schedule]:
        """The compiled circuit (once per daemon) whose hash must equal the peer's. An
        uncompiled circuit's hash is checked on its interface (the netlist, unscheduled,
        within the AND limit) before anything is scheduled or cached: a request naming
        a circuit with a wrong hash costs no compile."""
        try:
            ready = registry.lookup(circuit_id)  # the common case: no thread hop
            if ready is not None and self._planned.get(circuit_id) == id(ready[1]):
                circuit, schedule = ready
            else:
                iface = await self.work(registry.interface, circuit_id,
                                        self.options.max_and_gates)
                _same_hash(circuit_id, iface.content_hash, content_hash)
                circuit, schedule = await self.work(_prepare, circuit_id,
                                                    self.options.max_and_gates)
                self._planned[circuit_id] = id(schedule)
        except registry.UnknownCircuit as exc:
            raise ProtocolError(UNKNOWN_CIRCUIT, str(exc)) from None
        except registry.CircuitTooLarge as exc:
            raise ProtocolError(TOO_LARGE, f"{exc} (this {self.role}'s --max-and-gates)") \
                from None
        _same_hash(circuit_id, circuit.content_hash(), content_hash)
        return circuit, schedule

    async def next_message(self, conn: Connection,
                           busy: Callable[[], bool]) -> tuple[dict[str, Any], int]:
        """The next message on a served connection; ProtocolError (timeout) once it has
        been silent for ``idle_timeout`` with nothing of its own under way (``busy``)."""
        while True:
            try:
                return await conn.recv(self.options.idle_timeout)
            except TimeoutError:
                if not busy():
                    raise ProtocolError(TIMEOUT, f"idle for {self.options.idle_timeout:g} "
                                                 f"s: closing the connection") from None

    async def ends_link(self, conn: Connection, kind: str, refusal: str) -> bool:
        """The end of every serving loop: a ``health_request`` is answered, a ``bye``
        ends the connection (True); any other kind the loop does not take is refused
        (ProtocolError, UNEXPECTED: ``refusal`` with the kind for its ``{}``)."""
        if kind == "health_request":
            await conn.send(self.health())
            return False
        if kind == "bye":
            return True
        raise ProtocolError(UNEXPECTED, refusal.format(kind))

    def admit(self, peer: str = "") -> None:
        """Count a new session (of client ``peer``, if known), or refuse it as busy when
        the daemon is full or stopping, or the peer holds its quota."""
        if self.stopping.is_set():
            raise ProtocolError(BUSY, f"the {self.role} is shutting down")
        if self.counters["active"] >= self.options.max_sessions:
            raise ProtocolError(BUSY, f"the {self.role} runs its maximum of "
                                      f"{self.options.max_sessions} sessions")
        if peer:
            self.claim(peer)
        self.counters["active"] += 1

    def claim(self, peer: str) -> None:
        """Count a session against client ``peer``'s quota (BUSY beyond it)."""
        if self._peer_sessions[peer] >= self.options.max_sessions_per_peer:
            raise ProtocolError(BUSY, f"{peer} runs its maximum of "
                                      f"{self.options.max_sessions_per_peer} sessions on "
                                      f"the {self.role} (--max-sessions-per-peer)")
        self._peer_sessions[peer] += 1

    def finish(self, peer: str, record: dict[str, Any]) -> None:
        """Free an admitted session and log its line (see ``log_session``)."""
        self.counters["active"] -= 1
        if not self.counters["active"]:  # still idle a moment later: give the frames back
            asyncio.get_running_loop().call_later(BODIES_IDLE_S, self._release_bodies)
        self.heap.session_ended()
        if peer:
            self._peer_sessions[peer] -= 1
            if self._peer_sessions[peer] <= 0:
                del self._peer_sessions[peer]
        self.log_session(peer=peer, **record)

    def _release_bodies(self) -> None:
        """An idle daemon keeps no recycled table frames: its memory follows its load (the
        next trim returns them), while back-to-back invocations reuse them."""
        if not self.counters["active"]:
            self.bodies.clear()

    def log_session(self, *, peer: str, sid: bytes, circuit: str, n_and: int,
                    bytes_in: int, bytes_out: int, seconds: float, outcome: str,
                    reason: str = "") -> None:
        """The one JSON line per session, and the counters it adds to."""
        self.metrics.session_ended(outcome, n_and, bytes_in, bytes_out, seconds)
        fields: dict[str, Any] = {"peer": peer, "sid": sid, "circuit": circuit,
                                  "and": n_and, "bytes_in": bytes_in,
                                  "bytes_out": bytes_out, "seconds": round(seconds, 4),
                                  "outcome": outcome}
        if reason:
            fields["reason"] = reason
        event(self.log, "session", logging.INFO if outcome == OK else logging.WARNING,
              **fields)

    # ---- listener ------------------------------------------------------------------------
    def _opened(self, conn: Connection) -> None:
        """A TLS connection is up (handshake done): serve it in its own task."""
        task = asyncio.get_running_loop().create_task(self._on_connect(conn))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _refused(self, exc: ssl.SSLError) -> None:
        """A TLS handshake failed (no or foreign certificate, TLS < 1.3 ...)."""
        self.metrics.refused["tls"] += 1
        event(self.log, "tls_refused", logging.WARNING, reason=str(exc))

    def _refusal(self, conn: Connection) -> ProtocolError | None:
        """Why a verified peer may not connect now: revoked, or over its quota."""
        identity = conn.identity
        if identity is None:
            return None
        if identity.revoked_by(self.revoked):
            return ProtocolError(REVOKED, f"certificate {identity.name} "
                                          f"({identity.fingerprint[:16]}...) is revoked")
        quota = self.options.max_connections_per_peer
        if identity.role == "client" and sum(
                c.peer_name == identity.name for c in self.connections) >= quota:
            return ProtocolError(BUSY, f"{identity.name} holds its maximum of {quota} "
                                       f"connections (--max-connections-per-peer)")
        return None

    async def serve(self, conn: Connection) -> None:
        """Serve ``conn`` with ``_serve_<its peer's role>`` until it ends."""
        async with self.serving(conn):
            await getattr(self, f"_serve_{conn.peer_role}")(conn)

    @contextlib.asynccontextmanager
    async def serving(self, conn: Connection) -> AsyncIterator[None]:
        """How a served connection ends: a protocol error is logged and closes it with
        that error for the peer; a peer that left is logged."""
        where = {"peer": conn.peer_name, "address": str(conn.peer),
                 "peer_role": conn.peer_role}
        try:
            yield
        except ProtocolError as exc:
            event(self.log, "protocol_error", logging.WARNING, **where, code=exc.code,
                  reason=exc.message)
            await conn.close(messages.error(exc.code, exc.message))
        except (ConnectionClosed, RemoteError, TimeoutError) as exc:
            event(self.log, self.gone_event, **where, reason=str(exc))

    async def _on_connect(self, conn: Connection) -> None:
        address = str(conn.peer)
        try:
            await accept(conn, self.capabilities(), self.allowed,
                         self.options.handshake_timeout, self._refusal)
        except (ProtocolError, RemoteError, ConnectionClosed, TimeoutError) as exc:
            # a container's health check presents the server's own certificate: not news
            own = conn.peer_role == self.role
            self.metrics.refused["self_check" if own else getattr(exc, "code",
                                                                  "handshake")] += 1
            event(self.log, "connection_rejected", logging.DEBUG if own else logging.WARNING,
                  peer=conn.peer_name, address=address, reason=str(exc))
            return
        self.connections.add(conn)
        try:
            event(self.log, "connection_open", peer=conn.peer_name, address=address,
                  peer_role=conn.peer_role)
            await self.serve(conn)
        except Exception as exc:  # a bug must not take the daemon down: report and drop
            self.log.exception("connection_error", extra={"snail_fields": {
                "peer": conn.peer_name, "address": address}})
            await conn.close(messages.error(INTERNAL, f"internal error: {exc!r}"))
        finally:
            self.connections.discard(conn)
            await conn.close()
            event(self.log, "connection_closed", peer=conn.peer_name, address=address,
                  peer_role=conn.peer_role, bytes_in=conn.bytes_in, bytes_out=conn.bytes_out)

    async def run(self, host: str, port: int, ctx: ssl.SSLContext) -> None:
        """Listen until SIGTERM/SIGINT, then shut down gracefully."""
        loop = asyncio.get_running_loop()
        loop.set_exception_handler(self._loop_error)
        sys.setswitchinterval(SWITCH_INTERVAL)
        loop.add_signal_handler(signal.SIGTERM, self.stopping.set)
        loop.add_signal_handler(signal.SIGINT, self._interrupt)
        if hasattr(signal, "SIGHUP"):
            loop.add_signal_handler(signal.SIGHUP, self.reload_revoked)
        _audit_handshakes(ctx, self._refused)
        server = await loop.create_server(
            lambda: Connection(MAX_FRAME, on_open=self._opened,
                               frame_timeout=self.options.session_timeout, pool=self.bodies),
            host, port, ssl=ctx,
            ssl_handshake_timeout=self.options.handshake_timeout)
        for sock in server.sockets:  # accepted links inherit it (conn.py module doc)
            prefer_bursts(sock)
        announce(self.log, "listening", host=host, port=server.sockets[0].getsockname()[1],
                 pid=os.getpid(), max_sessions=self.options.max_sessions,
                 max_and_gates=self.options.max_and_gates,
                 workers=self.options.workers, revoked=len(self.revoked))
        scrapes = await self._serve_metrics()
        await self.stopping.wait()
        if scrapes is not None:
            scrapes.close()
        event(self.log, "shutting_down", active=self.counters["active"])
        server.close()
        deadline = time.monotonic() + (0 if self.interrupted else self.options.grace)
        while self.counters["active"] and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        if self.interrupted:  # sessions end now, each with an error to its peers
            await self._drain_handlers(timeout=0)
        await self.shutdown_extra()
        await asyncio.gather(*(c.close(messages.make("bye"), timeout=0.5)
                               for c in list(self.connections)), return_exceptions=True)
        await self._drain_handlers(timeout=1.0)
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(server.wait_closed(), 1.0)
        self.pool.shutdown(wait=False, cancel_futures=True)
        announce(self.log, "stopped", **self.metrics.health())

    async def _serve_metrics(self) -> asyncio.AbstractServer | None:
        if self.options.metrics is None or self.options.tls_dir is None:
            return None
        host, port = self.options.metrics
        server = await serve_scrapes(host, port,
                                     scrape_context(self.options.tls_dir, self.role),
                                     self.prometheus, self.health)
        announce(self.log, "metrics", host=host, port=server.sockets[0].getsockname()[1])
        return server

    def reload_revoked(self) -> None:
        """SIGHUP: reread revoked.txt; connections of peers it now lists are dropped."""
        if self.options.tls_dir is None:
            return
        try:
            self.revoked = read_revoked(Path(self.options.tls_dir))
        except TLSFileError as exc:  # keep the old list rather than admit everyone
            event(self.log, "revocations_unreadable", logging.ERROR, reason=str(exc))
            return
        dropped = [c for c in self.connections
                   if c.identity is not None and c.identity.revoked_by(self.revoked)]
        loop = asyncio.get_running_loop()
        for conn in dropped:
            task = loop.create_task(conn.close(messages.error(
                REVOKED, f"certificate {conn.peer_name} was revoked"), timeout=0.5))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        announce(self.log, "revocations_reloaded", revoked=len(self.revoked),
                 dropped=len(dropped))

    def _interrupt(self) -> None:
        """Ctrl-C: an operator wants the daemon gone: no grace period for sessions."""
        self.interrupted = True
        self.stopping.set()

    async def _drain_handlers(self, timeout: float) -> None:
        """Let connection handlers log their ends before ``stopped`` (supervisors read
        ``stopped`` as the last word); cancel any that overrun ``timeout``."""
        if not self._tasks:
            return
        _, late = ((set(), set(self._tasks)) if timeout <= 0
                   else await asyncio.wait(set(self._tasks), timeout=timeout))
        for task in late:
            task.cancel()
        await asyncio.gather(*late, return_exceptions=True)

    def _loop_error(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        """asyncio's unhandled errors (e.g. failed TLS handshakes) as structured logs."""
        exc = context.get("exception")
        event(self.log, "loop_error", logging.WARNING, message=context.get("message", ""),
              error=repr(exc) if exc else "")


def _audit_handshakes(ctx: ssl.SSLContext, refused: Callable[[ssl.SSLError], None]) -> None:
    """Report failed handshakes: the event loop drops them silently (they never reach a
    protocol), so the TLS objects of ``ctx`` report them on the way out."""

    class AuditedSSLObject(ssl.SSLObject):
        def do_handshake(self) -> None:
            try:
                super().do_handshake()
            except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
                raise
            except ssl.SSLError as exc:
                refused(exc)
                raise

    ctx.sslobject_class = AuditedSSLObject


def _same_hash(circuit_id: str, ours: str, theirs: str) -> None:
    if ours != theirs:
        raise ProtocolError(CIRCUIT_MISMATCH, f"circuit {circuit_id} has content hash "
                                              f"{ours[:16]}... here, the peer has "
                                              f"{theirs[:16]}...")


def _prepare(circuit_id: str, max_and: int) -> tuple[Circuit, Schedule]:
    """Compile (or load) the circuit and build its engine plan once."""
    circuit, schedule = registry.compiled(circuit_id, max_and)
    plan_for(schedule)
    return circuit, schedule


def run_daemon(daemon: Daemon, listen: tuple[str, int], ctx: ssl.SSLContext) -> bool:
    """Run ``daemon`` until it is stopped, on uvloop (asyncio's own loop on Windows,
    where uvloop does not exist); True if it was interrupted (SIGINT)."""
    if sys.platform == "win32":
        asyncio.run(daemon.run(*listen, ctx))
        return daemon.interrupted
    import uvloop

    uvloop.run(daemon.run(*listen, ctx))
    return daemon.interrupted
