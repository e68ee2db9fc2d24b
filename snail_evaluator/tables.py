"""The garbler's half of an evaluator session: its table stream, buffered while the
client's labels are awaited (garble-ahead, within the daemon's budget), evaluated in the
worker pool as frames arrive, then the outputs to the client. Mixed into
``EvaluatorDaemon``, whose session book (``daemon.py``) it uses."""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import Any

from snail_common.circuit.schedule import Schedule
from snail_common.gc import StreamError
from snail_common.gc.stream import SCHEME_HALF_GATES, scheme_id
from snail_common.net import messages
from snail_common.net.chunks import write_labels
from snail_common.net.conn import Connection
from snail_common.net.errors import (
    ABORTED,
    DUPLICATE_SESSION,
    PEER_LOST,
    STREAM,
    TIMEOUT,
    UNEXPECTED,
    ConnectionClosed,
    ProtocolError,
)

from .attest import Attested
from .lanes import EvalLane, Solo
from .session import Session, StreamCut


class GarblerSide(Attested):
    """The evaluator's garbler connections."""

    async def _serve_garbler(self, conn: Connection) -> None:
        while True:
            # idle between sessions (a pooled connection): closed after --idle-timeout;
            # a TLS connection whose data link carries the sessions is busy while it lives
            msg, size = await self.next_message(
                conn, lambda: not conn.data_link and conn.tied_open)
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
            ended = self.ended.get(sid)
            if ended is not None:  # its client's half failed or was refused already
                await self._end_stream(conn, sid, ended)
                return
            try:
                s = self._open(msg, size)  # the garbler came first
            except ProtocolError as exc:  # busy, draining: the stream ends unread
                self.remember_ended(sid, exc)
                await self._end_stream(conn, sid, exc)
                return
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
                ev, received, ahead, t_labels, waited = await self._evaluate(conn, s,
                                                                             schedule)
                await self._attested(conn, s)  # the garbler's signed digest (attest.py)
            finally:
                self.counters["streaming"] -= 1
            received += size
            t_done = time.monotonic()
            s.timeline["eval_end"] = time.time()
            outputs = self._outputs(ev)
            if s.failure is not None:  # cancelled while the last frame was evaluated
                raise StreamCut(garbler_ended=False)
        except StreamCut as cut:  # the session ended, the stream is sound: keep the link
            await self._end_stream(conn, sid, s.failure, answered=cut.garbler_ended,
                                   read=s.read_ahead)
            return
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
        # the garbler may have stopped waiting for this (it times out, or went): the
        # result is still the client's, and the session must end either way
        with contextlib.suppress(ConnectionClosed):
            s.bytes_out += conn.write(messages.make("done", sid=sid))
        try:
            s.bytes_out += write_labels(s.client, "output_labels", sid, outputs)
            s.bytes_out += s.client.write(messages.make(
                "stats", sid=sid, traffic={"garbler_to_evaluator": received,
                                           "garbled_ahead": ahead},
                timing={"ahead_s": t_labels - t0, "wait_s": waited,
                        "evaluate_s": t_done - t_labels, "lanes": float(ev.lanes),
                        **{f"t_{k}": v for k, v in s.timeline.items()}, **s.check_s},
                **self._forwarded(s)))
        except ConnectionClosed:
            pass  # the client left after its labels arrived: nobody to tell
        self._complete(s)
        with contextlib.suppress(ConnectionClosed):
            await s.client.drain()
        await conn.drain()

    async def _end_stream(self, conn: Connection, sid: bytes, why: ProtocolError,
                          answered: bool = False,
                          read: tuple[dict[str, Any], int] | None = None) -> None:
        """A session ended before its stream did (refused, cancelled, evicted, timed
        out): tell the garbler why, and unless its own ``error`` {sid} already ``answered``
        that, read on (from the message already ``read``, if any), discarding the
        session's frames and signed digest, until it comes: the connection is then in
        step for the next session (snail_garbler/streams.py)."""
        conn.post(messages.error(why.code, why.message, sid))
        while not answered:
            msg, _ = read or await conn.recv(self.options.session_timeout)
            read = None
            if msg["t"] in ("tables", "tables_end") and msg["sid"] == sid:
                if isinstance(msg.get("data"), memoryview):
                    conn.recycle(msg["data"])
                continue
            if msg["t"] != "error" or msg.get("sid") != sid:
                raise ProtocolError(UNEXPECTED, f"the garbler sent {msg['t']} after the "
                                                f"end of the session it was streaming")
            answered = True
        with contextlib.suppress(ConnectionClosed):
            await conn.drain()

    async def _evaluate(self, conn: Connection, s: Session, schedule: Schedule,
                        ) -> tuple[Solo | EvalLane, int, int, float, float]:
        """Read the table stream of ``s``; evaluate it once the client's labels are in.

        Garbling does not depend on inputs, so a client may have the garbler garble ahead:
        until its labels arrive, frames are buffered (up to ``ahead_bytes`` over all
        sessions; beyond that the stream waits, and TCP holds the garbler back). The
        watchdog bounds the wait for labels; once evaluating, a stalled stream times out.
        With lanes on, the session joins a batch when its labels come (lanes.py) and,
        once its own stream is in, waits for the batch's pass to end.
        Returns the evaluation, the bytes received, how many of them came before the
        labels, when the labels arrived, and how long the evaluation then waited for
        table frames (the server link's share of the invocation: never part of the
        evaluator's own work). The table frames' arrival and the labels' are stamped in
        ``s.timeline``."""
        received, ahead, timeout = 0, 0, self.options.session_timeout
        waited = 0.0
        laned = scheme_id(s.scheme) == SCHEME_HALF_GATES  # lanes batch half-gates sessions only
        buffered: list[bytes | memoryview] = []
        ev: Solo | EvalLane | None = None
        t_labels = time.monotonic()
        recv: asyncio.Future | None = None
        try:
            while ev is None or not ev.stream_complete:
                if s.failure is not None:  # its client cancelled, a timeout, an eviction
                    raise StreamCut(garbler_ended=False)
                if ev is None and s.ready.done():
                    ev = self._digested(s, await self.lanes.lane(s.circuit, schedule,
                                                                 s.ready.result())
                                        if laned else Solo(schedule, s.ready.result(),
                                                           scheme_id(s.scheme)))
                    if s.watchdog:
                        s.watchdog.cancel()
                    t_labels = time.monotonic()
                    s.timeline["labels"] = time.time()
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
                t_wait = time.monotonic()
                msg, size = await recv
                if ev is not None:  # evaluating, and this frame was not there yet
                    waited += time.monotonic() - t_wait
                recv = None
                received += size
                s.bytes_in += size
                if msg["t"] == "error" and msg.get("sid") == s.sid:  # it ended the stream
                    self._fail(s, ProtocolError(msg["code"], f"the garbler reported: "
                                                             f"{msg['message']}"))
                    raise StreamCut(garbler_ended=True)
                if s.failure is not None:
                    if msg["t"] == "tables" and isinstance(msg["data"], memoryview):
                        conn.recycle(msg["data"])
                    raise StreamCut(garbler_ended=False)
                if self._tables_end(s, msg, ev is not None):  # its signed digest: attest.py
                    continue
                if msg["t"] != "tables" or msg["sid"] != s.sid:
                    raise ProtocolError(UNEXPECTED, f"expected tables of this session, the "
                                                    f"garbler sent {msg['t']}")
                s.timeline.setdefault("first_received", time.time())
                s.timeline["last_received"] = time.time()
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
                self._read_ahead(s, recv)  # it may hold the signed digest (attest.py)
        return ev, received, ahead, t_labels, waited

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
