"""The evaluator daemon: evaluates garbled tables on the client's active input labels.

Protocol (messages in snail_common.net.messages). Two kinds of peers connect:

- a client (certificate role ``client``), one connection per localization: per
  invocation it sends ``session_start`` {sid, circuit, hash} and its active input labels
  (``input_labels`` chunks); it gets the active output labels (``output_labels`` chunks)
  and a ``stats`` message, or an ``error`` {sid}. Its ``error`` {sid} cancels a session.
- the garbler (role ``garbler``), over pooled connections carrying one session at a time:
  ``session_start`` {sid, circuit, hash}, then ``tables`` {sid, data} frames until the
  circuit's last AND gate; the evaluator answers ``done`` {sid}, or ``error`` {sid} and
  closes the connection (the rest of a broken stream cannot be skipped safely).

The two halves of a session meet by sid, in either order; both must name the same circuit
and content hash as the evaluator's own compiled copy. Frames are evaluated as they
arrive (in the worker pool), overlapping with the garbler producing the next ones; the
connection reads at most a few frames ahead, so a session holds a few MiB beyond its
wire labels. A session whose other half does not arrive, or whose stream stalls, for
``--session-timeout`` seconds fails; so does one whose garbler connection breaks. The
client always gets an ``error`` naming what happened, and the session is freed (see the
``health`` counters). The evaluator never receives a seed or the offset delta.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from snail_common.circuit.ir import FIRST_INPUT
from snail_common.circuit.schedule import Schedule
from snail_common.gc import StreamError
from snail_common.gc.stream import DEFAULT_SCHEME, SCHEME_HALF_GATES, scheme_id
from snail_common.net import messages
from snail_common.net.chunks import LabelAssembler, write_labels
from snail_common.net.conn import Connection
from snail_common.net.errors import (
    ABORTED,
    BAD_REQUEST,
    BUSY,
    DUPLICATE_SESSION,
    PEER_LOST,
    STREAM,
    TIMEOUT,
    UNEXPECTED,
    ConnectionClosed,
    ProtocolError,
)
from snail_common.net.metrics import OK
from snail_common.net.service import Daemon, Options
from snail_common.pnp.spec import owner_bits

from .lanes import EvalLane, LaneBatcher, Solo
from .owner import EarlyOwnerLabels

# input-label bytes a session may send before its circuit is loaded: far above the
# largest circuit's inputs (n = 4096 points take about 10 MB), far below a memory risk
MAX_EARLY_LABEL_BYTES = 64 << 20


@dataclass(eq=False)
class Session:
    """One invocation, from whichever half arrives first until it is done or failed."""

    sid: bytes
    circuit: str
    hash: str
    ready: asyncio.Future  # the complete input labels, or the failure
    client: Connection | None = None
    garbler: bool = False
    labels: LabelAssembler | None = None
    failure: ProtocolError | None = None
    started: float = field(default_factory=time.monotonic)
    watchdog: asyncio.TimerHandle | None = None
    peer: str = ""  # the client's certificate name, once its half has arrived
    n_and: int = 0
    bytes_in: int = 0
    bytes_out: int = 0
    queued: int = 0  # table bytes buffered while the labels are awaited
    scheme: str = DEFAULT_SCHEME  # as both halves declared it; the stream header must agree
    early: list[tuple[dict[str, Any], int]] = field(default_factory=list)  # labels that
    # came while the circuit was still loading, replayed once it is
    early_bytes: int = 0  # their wire size
    owner: LabelAssembler | None = None  # the map owner's wires, if the circuit has any

    def record(self, outcome: str, reason: str = "") -> dict:
        """This session's log line fields (see Daemon.log_session)."""
        return {"sid": self.sid, "circuit": self.circuit, "n_and": self.n_and,
                "bytes_in": self.bytes_in, "bytes_out": self.bytes_out,
                "seconds": time.monotonic() - self.started, "outcome": outcome,
                "reason": reason}


class EvaluatorDaemon(Daemon):
    role = "evaluator"
    allowed = ("client", "garbler", "mapowner")

    def __init__(self, options: Options, logger: logging.Logger) -> None:
        super().__init__(options, logger)
        self.sessions: dict[bytes, Session] = {}
        self.lanes = LaneBatcher(options.lane_window_ms / 1000, options.max_lanes)
        self.owner_early = EarlyOwnerLabels()

    @property
    def ahead_buffered(self) -> int:
        """Table bytes held for sessions still awaiting labels (the queued_bytes gauge)."""
        return self.counters["queued_bytes"]

    @ahead_buffered.setter
    def ahead_buffered(self, value: int) -> None:
        self.counters["queued_bytes"] = value

    # ---- session bookkeeping ---------------------------------------------------------------
    def _open(self, msg: dict[str, Any], size: int, peer: str = "") -> Session:
        self.admit(peer)
        s = Session(msg["sid"], msg["circuit"], msg["hash"],
                    asyncio.get_running_loop().create_future(), peer=peer, bytes_in=size,
                    scheme=msg.get("scheme", DEFAULT_SCHEME))
        s.ready.add_done_callback(_consume)
        self.sessions[s.sid] = s
        return s

    def _arm(self, s: Session) -> None:
        """Once this daemon has the circuit, the other half has ``session_timeout`` to
        show up (compiling is not idleness: the watchdog starts after it)."""
        if s.watchdog is None and s.failure is None:
            s.watchdog = asyncio.get_running_loop().call_later(
                self.options.session_timeout, self._expire, s)

    def _expire(self, s: Session) -> None:
        """The watchdog fired. A garbled-ahead session whose client is still busy with an
        earlier session here is queued, not idle: it waits on, up to ``--idle-timeout``
        in all (under load an invocation takes longer than ``--session-timeout``)."""
        s.watchdog = None
        if s.garbler and s.labels is not None and self._client_busy(s):
            waited = time.monotonic() - s.started
            left = self.options.idle_timeout - waited
            if left > 0:
                s.watchdog = asyncio.get_running_loop().call_later(
                    min(self.options.session_timeout, left), self._expire, s)
                return
        missing = ("the garbler's table stream" if not s.garbler
                   else "the map owner's labels" if s.labels is not None and s.labels.complete
                   else "the client's input labels")
        self._fail(s, ProtocolError(TIMEOUT, f"{missing} did not arrive within "
                                             f"{self.options.session_timeout:g} s"))

    def _client_busy(self, s: Session) -> bool:
        """Whether the client of ``s`` has an earlier session still under way here."""
        return any(x.client is s.client and x.started < s.started and x is not s
                   for x in self.sessions.values())

    def _fail(self, s: Session, exc: ProtocolError) -> None:
        """End ``s`` with ``exc``: tell the client, wake the garbler side, free it."""
        if self.sessions.get(s.sid) is not s:
            return
        del self.sessions[s.sid]
        s.failure = exc
        if s.watchdog:
            s.watchdog.cancel()
        if not s.ready.done():
            s.ready.set_exception(exc)
        if s.client is not None:
            s.client.post(messages.error(exc.code, exc.message, s.sid))
        self.finish(s.peer, s.record(exc.code, exc.message))

    def _complete(self, s: Session) -> None:
        del self.sessions[s.sid]
        self.finish(s.peer, s.record(OK))

    def _check_same(self, s: Session, msg: dict[str, Any]) -> None:
        if (msg["circuit"], msg["hash"]) != (s.circuit, s.hash):
            raise ProtocolError(BAD_REQUEST, f"client and garbler disagree on the circuit "
                                             f"of this session ({s.circuit} vs "
                                             f"{msg['circuit']})")
        if msg.get("scheme", DEFAULT_SCHEME) != s.scheme:
            raise ProtocolError(BAD_REQUEST, f"client and garbler disagree on the garbling "
                                             f"scheme of this session ({s.scheme} vs "
                                             f"{msg.get('scheme', DEFAULT_SCHEME)})")

    # ---- the client side -------------------------------------------------------------------
    async def _serve_client(self, conn: Connection) -> None:
        """A client's messages, each handled at once: a circuit being loaded or compiled
        for a session does not hold up the connection (a client probes a quiet link with
        ``health_request`` and gives it up if unanswered)."""
        loading: set[asyncio.Task] = set()
        try:
            while True:
                msg, size = await self.next_message(
                    conn, lambda: any(s.client is conn for s in self.sessions.values()))
                kind = msg["t"]
                if kind == "session_start":
                    s = self._client_start(conn, msg, size)
                    if s is not None:
                        task = asyncio.get_running_loop().create_task(self._client_load(s))
                        loading.add(task)
                        task.add_done_callback(loading.discard)
                elif kind == "input_labels":
                    self._client_labels(conn, msg, size)
                elif kind == "error" and "sid" in msg:
                    s = self.sessions.get(msg["sid"])
                    if s is not None and s.client is conn:
                        self._fail(s, ProtocolError(ABORTED, "cancelled by the client"))
                elif await self.ends_link(conn, kind, "a client may not send {} to the "
                                                      "evaluator"):
                    return
        finally:
            for task in loading:
                task.cancel()
            for s in [s for s in self.sessions.values() if s.client is conn]:
                self._fail(s, ProtocolError(ABORTED, "the client disconnected"))

    def _client_start(self, conn: Connection, msg: dict[str, Any],
                      size: int) -> Session | None:
        """The client's half of a session (None if refused: the client was told)."""
        sid = msg["sid"]
        try:
            s = self.sessions.get(sid)
            if s is None:
                s = self._open(msg, size, conn.peer_name)
            elif s.client is not None:
                raise ProtocolError(DUPLICATE_SESSION, "session id already in use")
            else:
                self._check_same(s, msg)
                self.claim(conn.peer_name)  # the garbler's half came first
                s.peer = conn.peer_name
                s.bytes_in += size
            s.client = conn
        except ProtocolError as exc:
            conn.post(messages.error(exc.code, exc.message, sid))
            if exc.code == BUSY:
                self.log_session(peer=conn.peer_name, sid=sid, circuit=msg["circuit"],
                                 n_and=0, bytes_in=size, bytes_out=0, seconds=0.0,
                                 outcome=exc.code, reason=exc.message)
            return None
        return s

    async def _client_load(self, s: Session) -> None:
        """Load (or compile) the session's circuit, then take the labels that came early."""
        try:
            circuit, schedule = await self.circuit(s.circuit, s.hash)
        except ProtocolError as exc:
            self._fail(s, exc)
            return
        s.n_and = schedule.n_and
        if s.failure is None:
            n_owner = owner_bits(circuit)
            s.labels = LabelAssembler("input_labels",
                                      FIRST_INPUT + schedule.n_inputs - n_owner)
            if n_owner:
                s.owner = LabelAssembler("owner_labels", n_owner)
                for msg, size in self.owner_early.take(s.sid):
                    self._add_labels(s, msg, size, owner=True)
            self._arm(s)
            early, s.early, s.early_bytes = s.early, [], 0
            for msg, size in early:
                self._add_labels(s, msg, size)

    def _client_labels(self, conn: Connection, msg: dict[str, Any], size: int) -> None:
        s = self.sessions.get(msg["sid"])
        if s is None or s.client is not conn:
            conn.post(messages.error(UNEXPECTED, "input labels for no session of yours "
                                                 "(never started, failed or finished)",
                                     msg["sid"]))
            return
        if s.labels is None:  # its circuit is still loading
            if s.early_bytes + size > MAX_EARLY_LABEL_BYTES:
                self._fail(s, ProtocolError(BAD_REQUEST, "more input labels than any "
                                                         "circuit takes"))
            elif s.failure is None:
                s.early.append((msg, size))
                s.early_bytes += size
            return
        self._add_labels(s, msg, size)

    def _add_labels(self, s: Session, msg: dict[str, Any], size: int,
                    owner: bool = False) -> None:
        """One chunk of the client's input labels (or, ``owner``, of the map owner's)."""
        s.bytes_in += size
        try:
            (s.owner if owner else s.labels).add(msg)
        except ProtocolError as exc:
            self._fail(s, exc)
            return
        self._check_inputs(s)

    def _check_inputs(self, s: Session) -> None:
        """Start evaluating once the client's labels (and the map owner's) are in."""
        if s.failure is None and s.labels.complete and not s.ready.done() and (
                s.owner is None or s.owner.complete):
            inputs = s.labels.labels()
            s.ready.set_result(inputs if s.owner is None
                               else np.concatenate([inputs, s.owner.labels()]))

    # ---- the map owner ---------------------------------------------------------------------
    async def _serve_mapowner(self, conn: Connection) -> None:
        """The map owner's link: the labels of its wires, by sid (owner.py)."""
        while True:
            msg, size = await self.next_message(conn, lambda: False)
            kind = msg["t"]
            if kind == "owner_labels":
                s = self.sessions.get(msg["sid"])
                if s is not None and s.owner is not None:
                    self._add_labels(s, msg, size, owner=True)
                else:
                    self.owner_early.add(msg, size)
            elif await self.ends_link(conn, kind, "the map owner may not send {} to the "
                                                  "evaluator"):
                return

    def finish(self, peer: str, record: dict) -> None:
        """A session ended: map-owner labels still waiting for it go too."""
        self.owner_early.drop(record["sid"])
        super().finish(peer, record)

    # ---- the garbler side ------------------------------------------------------------------
    async def _serve_garbler(self, conn: Connection) -> None:
        while True:
            # idle between sessions (a pooled connection): closed after --idle-timeout
            msg, size = await self.next_message(conn, lambda: False)
            kind = msg["t"]
            if kind == "session_start":
                await self._garbler_session(conn, msg, size)
            elif await self.ends_link(conn, kind, "the garbler sent {} outside a session"):
                return

    async def _garbler_session(self, conn: Connection, msg: dict[str, Any],
                               size: int) -> None:
        sid = msg["sid"]
        s = self.sessions.get(sid)
        if s is None:
            # the garbler came first; ProtocolError (busy) closes conn
            s = self._open(msg, size)
        elif s.garbler:
            raise ProtocolError(DUPLICATE_SESSION, "session id already streaming")
        else:
            s.bytes_in += size
        s.garbler = True
        t0 = time.monotonic()
        try:
            self._check_same(s, msg)
            _, schedule = await self.circuit(msg["circuit"], msg["hash"])
            self._arm(s)
            self.counters["streaming"] += 1
            try:
                ev, received, ahead, t_labels = await self._evaluate(conn, s, schedule)
            finally:
                self.counters["streaming"] -= 1
            received += size
            t_done = time.monotonic()
            outputs = ev.output_labels()
        except ProtocolError as exc:
            self._fail(s, ProtocolError(exc.code, f"the garbler's table stream: {exc.message}"))
            raise ProtocolError(exc.code, exc.message) from None  # closes the garbler conn
        except (ConnectionClosed, TimeoutError) as exc:
            code = TIMEOUT if isinstance(exc, TimeoutError) else PEER_LOST
            self._fail(s, ProtocolError(code, f"the garbler's table stream broke off: {exc}"))
            raise ConnectionClosed(str(exc)) from None
        except asyncio.CancelledError:
            self._fail(s, ProtocolError(ABORTED, "the evaluator is shutting down"))
            raise
        if s.failure is not None:  # cancelled while the last frame was evaluated
            raise ProtocolError(s.failure.code, s.failure.message)
        # the garbler may have stopped waiting for this (it times out, or went): the
        # result is still the client's, and the session must end either way
        with contextlib.suppress(ConnectionClosed):
            s.bytes_out += conn.write(messages.make("done", sid=sid))
        try:
            s.bytes_out += write_labels(s.client, "output_labels", sid, outputs)
            s.bytes_out += s.client.write(messages.make(
                "stats", sid=sid, traffic={"garbler_to_evaluator": received,
                                           "garbled_ahead": ahead},
                timing={"wait_s": t_labels - t0, "evaluate_s": t_done - t_labels,
                        "lanes": float(ev.lanes)}))
        except ConnectionClosed:
            pass  # the client left after its labels arrived: nobody to tell
        self._complete(s)
        with contextlib.suppress(ConnectionClosed):
            await s.client.drain()
        await conn.drain()

    async def _evaluate(self, conn: Connection, s: Session,
                        schedule: Schedule) -> tuple[Solo | EvalLane, int, int, float]:
        """Read the table stream of ``s``; evaluate it once the client's labels are in.

        Garbling does not depend on inputs, so a client may have the garbler garble ahead:
        until its labels arrive, frames are buffered (up to ``ahead_bytes`` over all
        sessions; beyond that the stream waits, and TCP holds the garbler back). The
        watchdog bounds the wait for labels; once evaluating, a stalled stream times out.
        With lanes on, the session joins a batch when its labels come (lanes.py) and,
        once its own stream is in, waits for the batch's pass to end.
        Returns the evaluation, the bytes received, how many of them came before the
        labels and when the labels arrived."""
        received, ahead, timeout = 0, 0, self.options.session_timeout
        laned = scheme_id(s.scheme) == SCHEME_HALF_GATES  # lanes batch half-gates sessions only
        buffered: list[bytes | memoryview] = []
        ev: Solo | EvalLane | None = None
        t_labels = time.monotonic()
        recv: asyncio.Future | None = None
        try:
            while ev is None or not ev.stream_complete:
                if ev is None and s.ready.done():  # raises the session's failure, if any
                    ev = (await self.lanes.lane(s.circuit, schedule, s.ready.result())
                          if laned else Solo(schedule, s.ready.result(), scheme_id(s.scheme)))
                    if s.watchdog:
                        s.watchdog.cancel()
                    t_labels = time.monotonic()
                    frames = list(buffered)
                    buffered.clear()
                    ahead = received
                    self.ahead_buffered -= s.queued
                    s.queued = 0
                    await self._feed(conn, ev, frames)
                    continue
                if ev is None and self._queue_full(s):
                    await asyncio.wait({s.ready})  # full: the stream waits for the labels
                    continue
                if recv is None:
                    recv = asyncio.ensure_future(conn.recv(None if ev is None else timeout))
                if ev is None:
                    await asyncio.wait({recv, s.ready}, return_when=asyncio.FIRST_COMPLETED)
                    if not recv.done():
                        continue
                msg, size = await recv
                recv = None
                received += size
                s.bytes_in += size
                if s.failure is not None:
                    raise ProtocolError(s.failure.code, s.failure.message)
                if msg["t"] == "error":
                    raise ProtocolError(msg["code"], f"the garbler reported: {msg['message']}")
                if msg["t"] != "tables" or msg["sid"] != s.sid:
                    raise ProtocolError(UNEXPECTED, f"expected tables of this session, the "
                                                    f"garbler sent {msg['t']}")
                if ev is None:
                    buffered.append(msg["data"])
                    self.ahead_buffered += len(msg["data"])
                    s.queued += len(msg["data"])
                else:
                    await self._feed(conn, ev, [msg["data"]])
            try:
                await asyncio.wait_for(ev.wait_done(), timeout)
            except asyncio.TimeoutError:
                raise TimeoutError(f"the other lanes of this session's batch stalled for "
                                   f"{timeout:g} s") from None
        except BaseException:
            if ev is not None:
                ev.drop()  # a batch goes on without this lane
            raise
        finally:
            if ev is not None and laned:
                self.lanes.release(s.circuit)
            self.ahead_buffered -= s.queued
            s.queued = 0
            if recv is not None:
                recv.cancel()
        return ev, received, ahead, t_labels

    def _queue_full(self, s: Session) -> bool:
        """No more garbled-ahead tables for ``s``: the daemon's buffer, or its client's
        share of it, is full."""
        if self.ahead_buffered >= self.options.ahead_bytes:
            return True
        # sessions whose client has not shown up yet share one peer's share
        peer_queued = sum(x.queued for x in self.sessions.values() if x.peer == s.peer)
        return peer_queued >= self.options.ahead_bytes_per_peer

    async def _feed(self, conn: Connection, ev: Solo | EvalLane,
                    frames: list[bytes | memoryview]) -> None:
        """Evaluate ``frames`` in the worker pool; then ``conn`` may receive into their
        buffers again (evaluation keeps no view of them)."""
        try:
            await self.work(_feed_all, ev, frames)
        except StreamError as exc:
            raise ProtocolError(STREAM, str(exc)) from None
        for data in frames:
            if isinstance(data, memoryview):
                conn.recycle(data)


def _feed_all(ev: Solo | EvalLane, frames: list[bytes | memoryview]) -> None:
    for data in frames:
        ev.feed(data)


def _consume(future: asyncio.Future) -> None:
    """Mark a failure as seen when no garbler half waits for it."""
    if not future.cancelled():
        future.exception()
