"""The garbler daemon: garbles circuits from client-chosen seeds and streams the tables.

Protocol (messages in snail_common.net.messages). A client keeps one TLS connection open
for a whole localization and sends one ``garble_request`` {sid, circuit, hash, seed, delta,
key} per invocation; requests run concurrently (up to ``--max-sessions``). For each:

1. compile (once per daemon, cached) the circuit and check the client's content hash;
2. take a TLS connection to the evaluator from the pool (or open one, authenticating
   with the garbler certificate), send ``session_start`` {sid, circuit, hash} and then the
   garbled tables as ``tables`` {sid, data} frames of ~1 MiB. Garbling of frame k+1 runs in
   the worker pool while frame k is written; ``drain`` stops the garbler when the
   evaluator falls behind, so a session holds a few MiB at most;
3. send the client the output zero-labels (``output_zero_labels`` chunks) and a ``stats``
   message with the bytes sent to the evaluator and timings;
4. the evaluator's verdict (``done`` {sid}, or ``error`` {sid}) is awaited with the
   connection, not the session (streams.py): a reservation's tables may wait at the
   evaluator for minutes, its slot here is free once they are sent. A session that ends
   early on either side leaves the connection in step; only a broken one is closed.

A request with ``ahead`` is a reservation (garbled before its client needs it): it is
admitted only where there is room, and a live request that meets a full garbler takes
its place (snail_common/net/slots.py); the reservation's client hears ``evicted``.

Failures reach the client as ``error`` {sid, code, message}. A client's ``error`` {sid}
cancels its session; a client that disconnects cancels all of its sessions. The garbler
never receives input labels.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import time
from collections.abc import Iterator
from typing import Any

from snail_common.circuit.schedule import Schedule
from snail_common.gc import Garbler, check_delta
from snail_common.gc.engine import resolve as resolve_engine
from snail_common.gc.stream import (
    DEFAULT_SCHEME,
    SCHEME_HALF_GATES,
    scheme_id,
    table_words,
)
from snail_common.net import messages
from snail_common.net.chunks import write_labels
from snail_common.net.conn import Connection, format_addr
from snail_common.net.errors import (
    ABORTED,
    BAD_REQUEST,
    DUPLICATE_SESSION,
    EVICTED,
    INTERNAL,
    PEER_LOST,
    TIMEOUT,
    ConnectionClosed,
    ProtocolError,
    RemoteError,
)
from snail_common.net.linkrates import LinkRates
from snail_common.net.logs import event
from snail_common.net.metrics import OK
from snail_common.net.replicas import Address, Replicas
from snail_common.net.service import Daemon, Options
from snail_common.net.tcpinfo import link_advice
from snail_common.net.tcpinfo import read as tcp_info

from .attest import Attesting
from .lanes import LaneBatcher, LaneView
from .owner import OwnerInputs
from .streams import State, TableLink, TableLinks

# why a session task was cancelled, as its log line and the client's error say
CANCELLED_BY_CLIENT = "cancelled by the client"
CLIENT_LEFT = "the client disconnected"
EVICTED_REASON = "a live session took the place of this one, garbled ahead (busy garbler)"
SHUTTING_DOWN = "the garbler is shutting down"
INLINE_INPUTS = 1 << 14
# frame sizing: aim for a frame every ~2 ms of garbling so that the evaluator overlaps
# even small or narrow circuits; the engine cost model is per AND gate plus per step.
# Beyond MAX_FRAMES frames a run overlaps no better, while every frame costs both daemons
# fixed work (thread hand-offs, a TLS write and read, decoding): n = 256 sent ~570 frames
# of ~0.4 MiB, now ~230 of 1 MiB. The native kernel garbles n = 6 in a few ms: 36 frames
# sized for numpy's pace made the hand-offs the garbler's largest cost (py-spy --gil),
# so its plan has ~6 frames of 1 MiB.
FRAME_SECONDS = 2e-3
MAX_FRAMES = 64
# seconds of garbling per AND gate and per step, by engine (this machine, loaded)
ENGINE_COSTS = {"numpy": (120e-9, 15e-6), "native": (20e-9, 0.3e-6)}
MIN_FRAME, MAX_FRAME_BYTES = 4 << 10, 1 << 20


def frame_plan(schedule: Schedule, scheme: int = SCHEME_HALF_GATES,
               engine: str = "numpy") -> tuple[int, int]:
    """(block_gates, frame_bytes) for garbling ``schedule`` on ``engine``: about
    FRAME_SECONDS of work per frame but at most MAX_FRAMES frames, between 4 KiB and 1 MiB;
    blocks of at most 8192 gates fill a frame."""
    per_and = 8 * table_words(scheme, 1 << 13) / (1 << 13)  # bytes per AND in the stream
    and_s, step_s = ENGINE_COSTS[engine]
    seconds = schedule.n_and * and_s + schedule.n_steps * step_s
    frames = min(MAX_FRAMES, max(1.0, seconds / FRAME_SECONDS))
    size = int(min(MAX_FRAME_BYTES, max(MIN_FRAME, per_and * schedule.n_and / frames)))
    block = 1 << max(7, min(13, int(size // per_and).bit_length() - 1))
    return block, max(size, 8 * table_words(scheme, block))


class GarblerDaemon(Attesting, Daemon):
    role = "garbler"
    allowed = ("client",)
    gone_event = "client_gone"

    def __init__(self, options: Options, logger: logging.Logger,
                 evaluators: tuple[Address, ...], client_ctx,
                 map_owners: tuple[Address, ...]) -> None:
        super().__init__(options, logger)
        # the only evaluators this garbler dials: what its operator's names resolve to;
        # a reservation's verdict may come once its client's labels did, which the
        # evaluator awaits up to its --idle-timeout
        self.links = TableLinks(Replicas(evaluators, "--evaluator", "evaluator"), client_ctx,
                                options.handshake_timeout,
                                options.session_timeout + options.idle_timeout, logger,
                                closed=self.connection_ended, table_link=options.table_link)
        self.table_streams: set[Connection] = set()  # sessions' tables under way
        self.lanes = LaneBatcher(options.lane_window_ms / 1000, options.max_lanes)
        self.owners = OwnerInputs(client_ctx, options.handshake_timeout, map_owners)
        # garbling rates (this engine's) and the server link, measured
        self.rates = LinkRates.for_engine(resolve_engine())
        self.advised = False  # tcp_advice logged

    async def serve(self, conn: Connection) -> None:
        """A client's requests. Its sessions end with the connection, once ``serving``
        has closed it: the client hears why, not each session's cancellation."""
        tasks: dict[bytes, asyncio.Task] = {}
        try:
            async with self.serving(conn):
                while True:
                    msg, size = await self.next_message(conn, lambda: bool(tasks))
                    kind = msg["t"]
                    if kind == "garble_request":
                        self._start(conn, msg, size, tasks)
                    elif kind == "error" and "sid" in msg:
                        task = tasks.get(msg["sid"])
                        if task is not None:
                            task.cancel(CANCELLED_BY_CLIENT)
                    elif await self.ends_link(conn, kind, "a client may not send {} to "
                                                          "the garbler"):
                        return
        finally:
            for task in tasks.values():
                task.cancel(CLIENT_LEFT)
            await asyncio.gather(*tasks.values(), return_exceptions=True)

    def _start(self, conn: Connection, req: dict[str, Any], size: int,
               tasks: dict[bytes, asyncio.Task]) -> None:
        sid = req["sid"]
        if sid in tasks:
            conn.post(messages.error(DUPLICATE_SESSION, "session id already in use", sid))
            return
        task = asyncio.get_running_loop().create_task(self._session(conn, req, size))
        tasks[sid] = task
        task.add_done_callback(lambda _: tasks.pop(sid, None))

    async def _session(self, client: Connection, req: dict[str, Any], size: int) -> None:
        sid, t0, t_wall, peer = req["sid"], time.monotonic(), time.time(), client.peer_name
        record = {"sid": sid, "circuit": req["circuit"], "n_and": 0, "bytes_in": size,
                  "bytes_out": 0, "seconds": 0.0, "outcome": OK}
        task = asyncio.current_task()
        try:  # here, not in _start: a task cancelled unstarted holds no slot
            slot = self.admit(peer, bool(req.get("ahead")),
                              evict=lambda: task.cancel(EVICTED_REASON))
        except ProtocolError as exc:
            self._fail(client, sid, exc.code, exc.message)
            self.log_session(peer=peer, **record | {"outcome": exc.code,
                                                    "reason": exc.message})
            return
        sent, running, link = 0, False, None
        try:
            circuit, schedule = await self.circuit(req["circuit"], req["hash"])
            record["n_and"] = schedule.n_and
            try:
                check_delta(req["delta"])
            except ValueError as exc:
                raise ProtocolError(BAD_REQUEST, f"field 'delta': {exc}") from None
            # the replica the client talks to, if the operator's names reach it
            link = await self.links.acquire(req.get("evaluator"), req.get("evaluator_id"))
            owner = await self.owners.feed(req, circuit, self.options.session_timeout,
                                           (format_addr(*link.where),
                                            link.conn.info.get("instance")))
            scheme = scheme_id(req.get("scheme", DEFAULT_SCHEME))
            record["scheme"] = req.get("scheme", DEFAULT_SCHEME)
            block, frame = frame_plan(schedule, scheme, self.engine.get("engine", "numpy"))
            garbler = None
            if scheme == SCHEME_HALF_GATES:  # lanes run half-gates only
                garbler = await self.lanes.lane(req["circuit"], schedule, req["seed"],
                                                req["delta"], req["key"], block, frame,
                                                client)
                running = True  # a run the batcher counts until it is released
            if garbler is None:
                make = functools.partial(Garbler, schedule, req["seed"], req["delta"],
                                         req["key"], block_gates=block,
                                         frame_bytes=frame, scheme=scheme)
                # deriving the input labels is AES over the inputs: inline unless large
                garbler = (make() if schedule.n_inputs < INLINE_INPUTS
                           else await self.work(make))
            t_ready = time.monotonic()
            self._streaming(link.conn, True)
            try:
                sent, timeline = await self._stream(link, garbler, req)
            finally:
                self._streaming(link.conn, False)
            t_streamed = time.monotonic()
            lanes = getattr(garbler, "lanes", 1)
            cpu_s = timeline.pop("cpu_s")
            if lanes == 1:  # a lane's thread may have garbled for the others
                self.rates.garbled(scheme, schedule.n_and, cpu_s)
            self.rates.streamed(tcp_info(link.conn.socket), [
                tcp_info(c.socket) for c in self.table_streams if c.peer == link.conn.peer])
            self._advise()
            timeline["request"] = t_wall
            record["timeline"] = timeline
            replied = record["bytes_out"] = self._reply(client, sid, garbler, sent, {
                "prepare_s": t_ready - t0, "garble_s": t_streamed - t_ready,
                "lanes": float(lanes), **{f"t_{k}": v for k, v in timeline.items()},
                **self.rates.report()}, owner)
            # the evaluator's verdict may come much later (a reservation's tables wait
            # for its client's labels): it is awaited with the link, not with this slot
            self.links.end(link, sid, OK, "")
            link = None
            if replied:
                with contextlib.suppress(ConnectionClosed):
                    await client.drain()
        except ProtocolError as exc:
            record.update(self._fail(client, sid, exc.code, exc.message))
        except RemoteError as exc:
            record.update(self._fail(client, sid, exc.code,
                                     f"the evaluator reported: {exc.message}"))
        except ConnectionClosed as exc:
            record.update(self._fail(client, sid, PEER_LOST, f"lost the evaluator: {exc}"))
        except TimeoutError as exc:
            record.update(self._fail(client, sid, TIMEOUT, str(exc)))
        except asyncio.CancelledError as exc:  # the reason is in the cancel, if any
            reason = exc.args[0] if exc.args else SHUTTING_DOWN
            record.update(self._fail(client, sid, EVICTED if reason == EVICTED_REASON
                                     else ABORTED, reason))
            raise
        except Exception as exc:  # a bug: the client must still hear of it
            self.log.exception("session_bug", extra={"snail_fields": {"sid": sid.hex()}})
            record.update(self._fail(client, sid, INTERNAL,
                                     f"internal error in the garbler: {exc!r}"))
        finally:
            if link is not None:  # ended early: the evaluator hears why (streams.py)
                self.links.end(link, sid, record["outcome"], record.get("reason", ""))
            if running:
                self.lanes.release(req["circuit"], client)
            record["bytes_out"] += sent
            record["seconds"] = time.monotonic() - t0
            self.finish(slot, record)

    def _advise(self) -> None:
        """Once the link is measured: log what this host's TCP settings cost the table
        stream (tcpinfo.link_advice), once per daemon."""
        if self.advised or self.rates.link_rate is None or self.rates.rtt_s is None:
            return
        self.advised = True
        for advice in link_advice(self.rates.link_rate, self.rates.rtt_s):
            event(self.log, "tcp_advice", logging.WARNING, advice=advice)

    def _reply(self, client: Connection, sid: bytes, garbler: Garbler | LaneView, sent: int,
               timing: dict[str, float], owner: dict[str, int]) -> int:
        """Queue the output zero-labels and stats for the client; the bytes queued (0 if
        it is gone)."""
        zero, signed = self.attest.reply(garbler, timing, client.peer_name)  # attest.py
        try:
            return (write_labels(client, "output_zero_labels", sid, zero)
                    + client.write(messages.make("stats", sid=sid,
                                                 traffic={"garbler_to_evaluator": sent,
                                                          **owner},
                                                 timing=timing, **signed)))
        except ConnectionClosed:
            event(self.log, "client_gone", peer=client.peer_name, sid=sid,
                  reason="before its result was sent")
            return 0

    @staticmethod
    def _fail(client: Connection, sid: bytes, code: str, message: str) -> dict[str, str]:
        """Tell the client its session failed; the session record's outcome."""
        client.post(messages.error(code, message, sid))
        return {"outcome": code, "reason": message}

    async def _stream(self, link: TableLink, garbler: Garbler | LaneView,
                      req: dict[str, Any]) -> tuple[int, dict[str, float]]:
        """Send session_start and every table frame; garbling of the next frame overlaps
        the sending of this one. Returns the bytes sent and the session's timeline: when
        the last frame was garbled and the first and last handed to the kernel (epoch
        seconds), and ``cpu_s``, the garbling threads' CPU. An ``error`` from the
        evaluator mid-stream raises RemoteError with the link in step (streams.py)."""
        sid, timeout = req["sid"], self.options.session_timeout
        evaluator = link.conn
        sent = link.start(messages.make("session_start", sid=sid, circuit=req["circuit"],
                                        hash=req["hash"],
                                        scheme=req.get("scheme", DEFAULT_SCHEME),
                                        ahead=bool(req.get("ahead"))))
        frames = self.attest.frames(garbler, req)  # hashed as sent (attest.py)
        clock = {"cpu_s": 0.0}
        pending = self.submit(_timed_next, frames, clock)
        timeline: dict[str, float] = {}
        try:
            while (data := await pending) is not None:
                if not evaluator.idle:  # the evaluator spoke: it ended the session
                    await link.verdict(sid, timeout)
                pending = self.submit(_timed_next, frames, clock)
                timeline.setdefault("first_sent", time.time())
                sent += evaluator.write(messages.make("tables", sid=sid, data=data))
                try:
                    await asyncio.wait_for(evaluator.drain(), timeout)
                except asyncio.TimeoutError:
                    link.state = State.BROKEN
                    raise TimeoutError(f"the evaluator took no tables for {timeout:g} s") \
                        from None
                timeline["last_sent"] = time.time()  # in the kernel's send buffer
            sent += evaluator.write(self.attest.end(garbler))  # the signed digest
            link.state = State.SENT
            timeline["garbled"] = clock.get("garbled", time.time())
        finally:
            if not pending.done():  # let the garbling thread finish with the generator
                await asyncio.gather(pending, return_exceptions=True)
        return sent, {**timeline, "cpu_s": clock["cpu_s"]}

    def _streaming(self, evaluator: Connection, under_way: bool) -> None:
        """Start or end a session's table stream on its own (taken, never shared)
        connection; the ``streaming`` gauge is the count of those under way."""
        if under_way:
            self.table_streams.add(evaluator)
        else:
            self.table_streams.discard(evaluator)
        self.counters["streaming"] = len(self.table_streams)

    def under_way(self) -> bool:
        """Sessions, and streams whose verdict is due: a reservation's tables at the
        evaluator still wait for its client (draining lets them be used)."""
        return super().under_way() or self.links.settling > 0

    async def shutdown_extra(self) -> None:
        await self.owners.close()
        await self.links.close()


def _timed_next(frames: Iterator[bytes | memoryview], clock: dict[str, float]
                ) -> bytes | memoryview | None:
    """The next table frame (None at the end), adding this thread's CPU seconds spent
    garbling it to ``clock["cpu_s"]`` (the garbler's own rate, whatever else the cores
    run) and stamping ``clock["garbled"]`` when a frame is done (epoch seconds)."""
    t0 = time.thread_time()
    try:
        frame = next(frames, None)
    finally:
        clock["cpu_s"] += time.thread_time() - t0
    if frame is not None:
        clock["garbled"] = time.time()
    return frame
