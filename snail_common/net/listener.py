"""A daemon's life as a TLS server: listening, admitting verified peers, revocation,
the metrics endpoint and shutdown.

SIGTERM drains: new sessions are refused as ``draining`` (retryable on another replica),
those under way finish for up to ``grace`` seconds (the listener stays open for the
connections they still need), then every peer gets ``bye`` and the daemon exits 0.
SIGINT ends the sessions at once. SIGHUP rereads ``revoked.txt`` and drops the
connections of peers it now lists. What a connection carries is the subclass's business
(``serve``); ``service.Daemon`` adds circuits, workers and session bookkeeping.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import secrets
import signal
import ssl
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from . import messages
from .conn import Connection, accept
from .dial import prefer_bursts
from .errors import BUSY, INTERNAL, REVOKED, ConnectionClosed, ProtocolError, RemoteError
from .frames import MAX_FRAME, BodyPool
from .logs import announce, event
from .metrics import Metrics
from .options import Options
from .scrape import scrape_context, serve_scrapes
from .tls import TLSFileError, read_revoked

# workers hold the GIL between numpy calls; a short switch interval lets the event loop
# (TLS, other sessions) in sooner than the default 5 ms
SWITCH_INTERVAL = 5e-4


class Listener:
    """The TLS server under a daemon: a subclass says what a verified connection gets
    (``serve``), what it announces (``capabilities``, ``health``, ``prometheus``) and
    closes its own resources (``shutdown_extra``)."""

    role = ""
    allowed: tuple[str, ...] = ()  # certificate roles that may connect

    def __init__(self, options: Options, logger: logging.Logger) -> None:
        self.options = options
        self.log = logger
        self.connections: set[Connection] = set()
        # received table frames kept for the next ones while sessions run, at most the
        # garbled-ahead budget (what buffered frames may hold anyway)
        self.bodies = BodyPool(options.ahead_bytes)
        self._tasks: set[asyncio.Task] = set()
        self.metrics = Metrics(self.role, lambda: len(self.connections))
        self.counters = self.metrics.gauges  # active, streaming, queued_bytes
        self.revoked = read_revoked(options.tls_dir) if options.tls_dir else frozenset()
        self.started = time.monotonic()
        self.stopping = asyncio.Event()
        self.interrupted = False
        # who this replica is: announced in capabilities, so that a client can name it to
        # the garbler, and a replica restarted on the same address is told apart
        self.instance = secrets.token_hex(8)

    # ---- what the subclass provides ------------------------------------------------------
    def capabilities(self) -> dict[str, Any]:
        raise NotImplementedError

    def health(self) -> dict[str, Any]:
        raise NotImplementedError

    def prometheus(self) -> str:
        raise NotImplementedError

    def startup_fields(self) -> dict[str, Any]:
        """What the ``listening`` line adds for this daemon."""
        return {}

    def capabilities_for(self, conn: Connection) -> dict[str, Any]:
        """The ``capabilities`` a verified peer gets (its role is known by now)."""
        return self.capabilities()

    async def listen(self, host: str, port: int, ctx: ssl.SSLContext,
                     factory: Callable[[], Connection]) -> Any:
        """The listening server: TLS connections made by ``factory`` (the evaluator
        shares its port with the table data links: sharedport.py)."""
        server = await asyncio.get_running_loop().create_server(
            factory, host, port, ssl=ctx, ssl_handshake_timeout=self.options.handshake_timeout)
        for sock in server.sockets:  # accepted links inherit it (dial.py module doc)
            prefer_bursts(sock)
        return server

    async def serve(self, conn: Connection) -> None:
        raise NotImplementedError

    async def shutdown_extra(self) -> None:
        """Close what the subclass owns (e.g. pooled outgoing connections)."""

    def connection_ended(self) -> None:
        """A served or dialled connection has closed (the daemon may give memory back)."""

    def under_way(self) -> bool:
        """Whether work a peer still counts on is under way (draining waits for it)."""
        return bool(self.counters["active"])

    # ---- connections ---------------------------------------------------------------------
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

    async def _on_connect(self, conn: Connection) -> None:
        address = str(conn.peer)
        try:
            await accept(conn, self.capabilities_for(conn), self.allowed,
                         self.options.handshake_timeout, self._refusal)
        except (ProtocolError, RemoteError, ConnectionClosed, TimeoutError) as exc:
            # a container's health check presents the server's own certificate: not news
            own = conn.peer_role == self.role
            self.metrics.refused["self_check" if own else getattr(exc, "code",
                                                                  "handshake")] += 1
            event(self.log, "connection_rejected", logging.DEBUG if own else logging.WARNING,
                  peer=conn.peer_name, address=address, reason=str(exc))
            return
        await self._serve_admitted(conn, address)

    def serve_later(self, conn: Connection) -> None:
        """Serve a connection admitted some other way (a data link, by its token) in a
        task of its own, as the TLS connections are."""
        task = asyncio.get_running_loop().create_task(
            self._serve_admitted(conn, str(conn.peer)))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _serve_admitted(self, conn: Connection, address: str) -> None:
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
            self.connection_ended()
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
        server = await self.listen(host, port, ctx, lambda: Connection(
            MAX_FRAME, on_open=self._opened, frame_timeout=self.options.session_timeout,
            pool=self.bodies))
        announce(self.log, "listening", host=host, port=server.sockets[0].getsockname()[1],
                 pid=os.getpid(), instance=self.instance,
                 max_sessions=self.options.max_sessions,
                 max_and_gates=self.options.max_and_gates,
                 workers=self.options.workers, revoked=len(self.revoked),
                 **self.startup_fields())
        scrapes = await self._serve_metrics()
        await self.stopping.wait()
        event(self.log, "shutting_down", active=self.counters["active"],
              draining=not self.interrupted)
        # draining: the listener stays open while sessions finish, since a session under
        # way may still need a connection (the garbler streaming to the evaluator that
        # admitted its client's half, the map owner's labels); new sessions are refused
        if self.interrupted:
            server.close()
        deadline = time.monotonic() + (0 if self.interrupted else self.options.grace)
        while self.under_way() and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        cut = self.counters["active"]  # under way when the grace ran out (or Ctrl-C came)
        server.close()
        if scrapes is not None:
            scrapes.close()
        if self.interrupted:  # sessions end now, each with an error to its peers
            await self._drain_handlers(timeout=0)
        await self.shutdown_extra()
        await asyncio.gather(*(c.close(messages.make("bye"), timeout=0.5)
                               for c in list(self.connections)), return_exceptions=True)
        await self._drain_handlers(timeout=1.0)
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(server.wait_closed(), 1.0)
        announce(self.log, "stopped", sessions_cut=cut, **self.metrics.health())

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



def run_daemon(daemon: Listener, listen: tuple[str, int], ctx: ssl.SSLContext) -> bool:
    """Run ``daemon`` until it is stopped, on uvloop (asyncio's own loop on Windows,
    where uvloop does not exist); True if it was interrupted (SIGINT)."""
    if sys.platform == "win32":
        asyncio.run(daemon.run(*listen, ctx))
        return daemon.interrupted
    import uvloop

    uvloop.run(daemon.run(*listen, ctx))
    return daemon.interrupted
