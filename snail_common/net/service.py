"""What both daemons share above the listener: compiled circuits, the worker pool, session
bookkeeping with per-peer quotas, health and metrics, and the one log line per session.

CPU work (compiling, garbling, evaluating) runs in a thread pool: numpy and AES release
the GIL, and the event loop stays free for other sessions, TLS and health requests.
The TLS server itself, revocation and shutdown are ``listener.Listener``'s.

Every session ends with one JSON log line ``{"event": "session", "peer", "circuit",
"and", "bytes_in", "bytes_out", "seconds", "outcome", "table_link"}`` (outcome ``ok`` or
an error code; ``table_link`` the daemon's ``--table-link``),
and the same numbers feed the counters of ``health`` and ``--metrics``.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import ssl
import time
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

from snail_common import failpoints
from snail_common.circuit import registry
from snail_common.circuit.ir import Circuit
from snail_common.circuit.plan import plan_for
from snail_common.circuit.schedule import Schedule
from snail_common.gc.native.run import program_for
from snail_common.gc.stream import BLOCK_GATES

from . import messages
from .conn import SOFTWARE, Connection
from .errors import (
    ABORTED,
    CIRCUIT_MISMATCH,
    DRAINING,
    EVICTED,
    TIMEOUT,
    TOO_LARGE,
    UNEXPECTED,
    UNKNOWN_CIRCUIT,
    ConnectionClosed,
    ProtocolError,
    RemoteError,
)
from .frames import MAX_FRAME
from .heap import HeapTrimmer, one_arena
from .listener import Listener
from .logs import event
from .metrics import OK
from .options import Options
from .slots import Slot, Slots

T = TypeVar("T")
# session outcomes that are the service working as meant: logged at info (a cancel by its
# client, a reservation giving its place to a live session), every other at warning
EXPECTED = frozenset({OK, ABORTED, EVICTED})
BODIES_IDLE_S = 1.0  # recycled table frames are dropped once the daemon is idle this long


class Daemon(Listener):
    """Base of the daemons; a subclass serves each certificate role of ``allowed`` in a
    method ``_serve_<role>(conn)`` that returns once the connection is done (or
    overrides ``serve``)."""

    gone_event = "peer_gone"  # the log line of a peer lost mid-connection

    def __init__(self, options: Options, logger: logging.Logger) -> None:
        super().__init__(options, logger)
        one_arena()  # before any worker thread: their memory is trimmed with the rest
        self.pool = ThreadPoolExecutor(options.workers, thread_name_prefix=self.role)
        self._planned: dict[str, int] = {}  # circuit id -> id() of the planned schedule
        self.slots = Slots(self.role, options.max_sessions, options.max_sessions_per_peer,
                           options.max_ahead_per_peer)
        self.heap = HeapTrimmer()
        self.engine: dict[str, str] = {}  # which garbling engine serves (use_engine)
        self._sweep: asyncio.TimerHandle | None = None  # connection_ended's pending sweep

    async def run(self, host: str, port: int, ctx: ssl.SSLContext) -> None:
        """Serve until stopped (``Listener.run``), then let the workers go."""
        try:
            await super().run(host, port, ctx)
        finally:
            self.pool.shutdown(wait=False, cancel_futures=True)

    # ---- helpers for subclasses ----------------------------------------------------------
    def capabilities(self) -> dict[str, Any]:
        return messages.make("capabilities", role=self.role, software=SOFTWARE,
                             max_frame=MAX_FRAME, families=list(registry.families()),
                             max_sessions=self.options.max_sessions,
                             max_and_gates=self.options.max_and_gates,
                             instance=self.instance)

    def use_engine(self, status: dict[str, str]) -> None:
        """Record which garbling engine serves (gc/engine.py's ``engine_status``), for
        the start-up line and ``health``."""
        self.engine = {"engine": status["engine"]}
        if "reason" in status:
            self.engine["engine_reason"] = status["reason"]
        if "threads" in status:  # the native kernel's threads per run
            self.engine["engine_threads"] = int(status["threads"])

    def startup_fields(self) -> dict[str, Any]:
        return {**self.engine, "table_link": self.options.table_link}

    def health(self) -> dict[str, Any]:
        armed = failpoints.armed()  # a daemon that misbehaves on purpose says so
        return messages.make("health", role=self.role, sessions=self.metrics.health(),
                             uptime_s=round(time.monotonic() - self.started, 3),
                             table_link=self.options.table_link, **self.engine,
                             **({"failpoints": armed} if armed else {}))

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
                                                    self.options.max_and_gates,
                                                    self.engine.get("engine") == "native")
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

    def admit(self, peer: str = "", ahead: bool = False,
              evict: Callable[[], None] | None = None) -> Slot:
        """A slot for a new session (of client ``peer``, if known; ``ahead``: a
        reservation, garbled before its client needs it), or ProtocolError: ``draining``
        when the daemon is stopping (SIGTERM: the client retries on another replica),
        ``busy`` when it is full (a live session first takes a reservation's place:
        slots.py, whose ``evict`` ends that session)."""
        if self.stopping.is_set():
            raise ProtocolError(DRAINING, f"the {self.role} is draining (stopping): it "
                                          f"finishes its sessions and takes no new one")
        slot = self.slots.admit(peer, ahead, evict)
        self._count_slots()
        return slot

    def claim(self, slot: Slot, peer: str) -> None:
        """Count a session whose client half came second against client ``peer``'s quota
        (BUSY beyond it)."""
        self.slots.claim(slot, peer)
        self._count_slots()

    def finish(self, slot: Slot | None, record: dict[str, Any]) -> None:
        """Free an admitted session's slot and log its line (see ``log_session``)."""
        if slot is not None:
            self.slots.release(slot)
            self._count_slots()
        if not self.counters["active"]:  # still idle a moment later: give the frames back
            self.connection_ended()
        self.heap.session_ended()
        self.log_session(peer=slot.peer if slot is not None else "", **record)

    def _count_slots(self) -> None:
        self.counters["active"] = self.slots.active
        self.counters["reserved"] = self.slots.reservations

    def connection_ended(self) -> None:
        """A session or a connection ended: once the daemon has been idle for
        BODIES_IDLE_S, give its memory back (``_release_bodies``). A connection that
        closes after the last session (a client leaving, a pooled link expiring) frees
        buffers of its own, so each end asks again (at most one sweep is pending)."""
        if self._sweep is None or self._sweep.cancelled():
            self._sweep = asyncio.get_running_loop().call_later(BODIES_IDLE_S,
                                                                self._release_bodies)

    def _release_bodies(self) -> None:
        """An idle daemon keeps no recycled table frames, and hands its freed heap back:
        its memory follows its load, while back-to-back invocations reuse the frames.
        Garbage in reference cycles (a closed connection and its transport, a session
        and its tasks, with their buffers) is collected first: an idle daemon allocates
        nothing, so the collector would otherwise not run until the next client."""
        self._sweep = None
        if not self.counters["active"]:
            self.bodies.clear()
            gc.collect()
            self.heap.trim()

    def log_session(self, *, peer: str, sid: bytes, circuit: str, n_and: int,
                    bytes_in: int, bytes_out: int, seconds: float, outcome: str,
                    reason: str = "", scheme: str = "",
                    timeline: dict[str, float] | None = None, **more: str) -> None:
        """The one JSON line per session, and the counters it adds to. ``timeline``:
        when this daemon saw the session's events (epoch seconds: comparable across
        hosts with synchronized clocks), e.g. the tables' first and last byte; ``more``:
        a role's own fields (the garbler's signing key and digest)."""
        self.metrics.session_ended(outcome, n_and, bytes_in, bytes_out, seconds)
        fields: dict[str, Any] = {"peer": peer, "sid": sid, "circuit": circuit,
                                  "and": n_and, "bytes_in": bytes_in,
                                  "bytes_out": bytes_out, "seconds": round(seconds, 4),
                                  "outcome": outcome,
                                  "table_link": self.options.table_link}
        if scheme:
            fields["scheme"] = scheme
        if reason:
            fields["reason"] = reason
        fields.update(more)
        if timeline:
            fields["timeline"] = {k: round(v, 6) for k, v in timeline.items()}
        event(self.log, "session", logging.INFO if outcome in EXPECTED else logging.WARNING,
              **fields)


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



def _same_hash(circuit_id: str, ours: str, theirs: str) -> None:
    if ours != theirs:
        raise ProtocolError(CIRCUIT_MISMATCH, f"circuit {circuit_id} has content hash "
                                              f"{ours[:16]}... here, the peer has "
                                              f"{theirs[:16]}...")


def _prepare(circuit_id: str, max_and: int, native: bool) -> tuple[Circuit, Schedule]:
    """Compile (or load) the circuit and build its engine plan once (and the native
    kernel's program of it for the usual block size: checking its indices takes a few
    tenths of a second at n = 256, which the first session need not wait for)."""
    circuit, schedule = registry.compiled(circuit_id, max_and)
    plan_for(schedule)
    if native:
        program_for(schedule, BLOCK_GATES)
    return circuit, schedule

