"""The map owner's daemon: it holds a map and feeds its points into the devices' circuits
without handing anyone a point in the clear, nor learning which points a device uses.

Two kinds of peers connect (snail_common.net.messages has the catalogue):

- a device (certificate role ``client``): ``map_info_request`` gets the published part of
  the map (sorted ids, normalizing similarity); after one round of base OTs
  (``ot_base_a``/``ot_base_b``, the device is the IKNP receiver) each ``ot_ext_u`` is one
  frame's oblivious selection (ot/selection.py): the device gets xyz ^ P for its secret
  indices in ``sel_table`` chunks with a fresh frame handle; the map owner keeps the pads P
  of that frame (at most ``max_frames`` frames, the oldest forgotten first). Per run,
  ``pad_correction_request`` {frame, sid} is answered with P ^ r, r being the random
  choices of that session's OT (pads.py): the device's share becomes xyz ^ r.
- the garbler (role ``garbler``), per session as it garbles it (ahead of its run):
  ``map_invocation`` {sid, count, evaluator}. The map owner inputs fresh random bits r:
  it is the receiver of a chosen-message IKNP OT whose sender is the garbler (base OTs
  once per connection, the map owner as the base-OT sender); it gets one label per wire,
  never the global offset, and forwards the labels to the evaluator (``owner_labels`` by
  sid), then answers the garbler ``done``. The garbler names the evaluator replica; the
  map owner dials it only if its own operator's ``--evaluator`` names reach it
  (snail_common.net.replicas), else the invocation is ``forbidden``.

It never receives a 2D point, a map id, a pose, a seed or the offset: no message carries
one to it.
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from collections import OrderedDict
from typing import Any

import numpy as np

from snail_common.loc.owner import POINT_BYTES, PublishedMap
from snail_common.net import messages
from snail_common.net.chunks import write_labels
from snail_common.net.conn import Connection, connect, format_addr
from snail_common.net.errors import (
    BAD_REQUEST,
    FORBIDDEN,
    PEER_LOST,
    UNEXPECTED,
    ConnectionClosed,
    ProtocolError,
    RemoteError,
)
from snail_common.net.logs import event
from snail_common.net.metrics import OK
from snail_common.net.replicas import Address, Replicas
from snail_common.net.service import Daemon, Options
from snail_common.ot import ExtReceiver, ExtSender
from snail_common.ot.carry import chunks, ot_part, pad_bits
from snail_common.ot.selection import SelectSender, index_bits

from .pads import SessionPads

MAX_FRAMES = 4096  # selections whose pads are kept (a frame's invocations need them)
PAD_BITS = POINT_BYTES * 8  # a point's pad: three float32 words
MAX_PAD_BITS = 1024 * PAD_BITS  # the largest circuit's (n <= 1,024: docs/map-owner.md)
NO_CIRCUIT = "map_owner"  # the circuit field of a session log line


class MapOwnerDaemon(Daemon):
    role = "mapowner"
    allowed = ("client", "garbler")

    def __init__(self, options: Options, logger: logging.Logger, published: PublishedMap,
                 values: np.ndarray, client_ctx, max_frames: int = MAX_FRAMES,
                 evaluators: tuple[Address, ...] = ()) -> None:
        super().__init__(options, logger)
        self.published, self.values = published, values
        self.client_ctx = client_ctx  # TLS context for the links to evaluators
        # the only evaluators this map owner dials (its operator's --evaluator names)
        self.evaluator_names = Replicas(evaluators, "--evaluator", "evaluator")
        self.frames: OrderedDict[bytes, np.ndarray] = OrderedDict()  # handle -> pads
        self.max_frames = max_frames
        self.evaluators: dict[tuple[str, int], Connection] = {}
        self.sessions = SessionPads()  # each session's random OT choices, until its run
        self._dialing: dict[tuple[str, int], asyncio.Lock] = {}

    # ---- devices (role client): published map and oblivious selection ------------------
    async def _serve_client(self, conn: Connection) -> None:
        ot: ExtSender | None = None
        while True:
            msg, size = await self.next_message(conn, lambda: False)
            kind = msg["t"]
            if kind == "map_info_request":
                self._send_map_info(conn)
                await conn.drain()
            elif kind == "ot_base_a":
                if ot is not None:
                    raise ProtocolError(UNEXPECTED, "base OTs were done on this connection")
                ot = ExtSender()
                await conn.send(messages.make("ot_base_b",
                                              b=(await self.work(ot.base_reply,
                                                                 ot_part(msg)))["b"]))
            elif kind == "ot_ext_u":
                if ot is None:
                    raise ProtocolError(UNEXPECTED, "a selection before the base OTs")
                await self._select(conn, ot, msg, size)
            elif kind == "pad_correction_request":
                self._correct(conn, msg)
            elif await self.ends_link(conn, kind, "a client may not send {} to the map "
                                                  "owner"):
                return

    def _send_map_info(self, conn: Connection) -> None:
        ids = self.published.ids_bytes()
        for offset, piece in chunks(ids, messages.DATA_CHUNK):
            conn.write(messages.make("map_info", points=len(self.published.ids),
                                     transform=self.published.transform_bytes(),
                                     start=offset // 4, ids=piece))

    async def _select(self, conn: Connection, ot: ExtSender, msg: dict[str, Any],
                      size: int) -> None:
        """One frame: the table of every point under this frame's fresh pads."""
        t0, frame = time.monotonic(), secrets.token_bytes(16)
        slot = self.admit(conn.peer_name)
        record = {"sid": frame, "circuit": NO_CIRCUIT, "n_and": 0, "bytes_in": size,
                  "bytes_out": 0, "seconds": 0.0, "outcome": OK}
        try:
            sender = SelectSender(ot, self.values)
            n = msg["m"] // index_bits(len(self.values))  # a ragged m: respond names it
            pads = np.frombuffer(secrets.token_bytes(max(n, 1) * self.values.shape[1]),
                                 np.uint8).reshape(max(n, 1), -1)
            answer = await self.work(sender.respond, ot_part(msg), pads)
            self._keep(frame, pads)
            table = answer["table"]
            for offset, piece in chunks(table, messages.DATA_CHUNK):
                record["bytes_out"] += conn.write(messages.make(
                    "sel_table", frame=frame, start=answer["start"], key=answer["key"],
                    offset=offset, total=len(table), table=piece))
                await conn.drain()
        except ProtocolError as exc:
            record.update(outcome=exc.code, reason=exc.message)
            raise
        finally:
            record["seconds"] = time.monotonic() - t0
            self.finish(slot, record)

    def _keep(self, frame: bytes, pads: np.ndarray) -> None:
        self.frames[frame] = pads
        while len(self.frames) > self.max_frames:
            self.frames.popitem(last=False)

    # ---- the garbler: the pads into each invocation -----------------------------------
    async def _serve_garbler(self, conn: Connection) -> None:
        ot: list[ExtReceiver] = []  # this link's OT session, once its base OTs are done
        while True:
            msg, size = await self.next_message(conn, lambda: False)
            kind = msg["t"]
            if kind == "map_invocation":
                await self._invocation(conn, ot, msg, size)
            elif await self.ends_link(conn, kind, "the garbler may not send {} to the map "
                                                  "owner"):
                return

    def _correct(self, conn: Connection, msg: dict[str, Any]) -> None:
        """Answer one run's ``pad_correction_request``: its frame's pad bits XOR its
        session's random choices (an ``error`` {sid} naming the field that does not fit)."""
        sid = msg["sid"]
        try:
            pads = self.frames.get(msg["frame"])
            if pads is None:
                raise ProtocolError(BAD_REQUEST, "field 'frame': no selection of this map "
                                                 "owner has that handle (unknown or "
                                                 "forgotten)")
            bits, chosen = pad_bits(pads), self.sessions.take(sid)
            if len(bits) != len(chosen):
                raise ProtocolError(BAD_REQUEST, f"field 'frame': the frame has {len(bits)} "
                                                 f"pad bits, the session's circuit "
                                                 f"{len(chosen)}")
            conn.write(messages.make("pad_correction", sid=sid, correction=np.packbits(
                bits ^ chosen, bitorder="little").tobytes()))
        except ProtocolError as exc:
            conn.post(messages.error(exc.code, exc.message, sid))

    async def _base_ots(self, conn: Connection, ot: list[ExtReceiver]) -> ExtReceiver:
        """The link's OT session: base OTs (the map owner as their sender) the first time."""
        if not ot:
            receiver = ExtReceiver()
            conn.write(messages.make("ot_base_a", a=receiver.start()["a"]))
            reply = await conn.expect("ot_base_b", self.options.session_timeout)
            await self.work(receiver.base_done, ot_part(reply))
            ot.append(receiver)
        return ot[0]

    async def _invocation(self, conn: Connection, ot: list[ExtReceiver],
                          msg: dict[str, Any], size: int) -> None:
        """Take the labels of fresh random bits by OT, forward them, keep the bits for
        the session's run (pads.py)."""
        sid, t0 = msg["sid"], time.monotonic()
        record = {"sid": sid, "circuit": NO_CIRCUIT, "n_and": 0, "bytes_in": size,
                  "bytes_out": 0, "seconds": 0.0, "outcome": OK}
        slot = self.admit()
        started = False  # once OT messages flow, a failure leaves this link out of step
        try:
            count = msg["count"]
            if not 0 < count <= MAX_PAD_BITS or count % PAD_BITS:
                raise ProtocolError(BAD_REQUEST, f"field 'count': a multiple of {PAD_BITS} "
                                                 f"up to {MAX_PAD_BITS}, got {count}")
            bits = np.unpackbits(np.frombuffer(secrets.token_bytes(count // 8), np.uint8),
                                 bitorder="little")
            evaluator = await self._locate(msg)  # before the OT: a refusal costs nothing
            started = True
            receiver = await self._base_ots(conn, ot)
            request = receiver.request(bits)
            record["bytes_out"] += conn.write(messages.make("ot_ext_u", sid=sid, **{
                k: request[k] for k in ("start", "m", "u")}))
            answer = await conn.expect("ot_ext_y", self.options.session_timeout)
            if answer.get("sid") != sid:
                raise ProtocolError(UNEXPECTED, "an OT answer for another session")
            labels = await self.work(receiver.receive, ot_part(answer))
            record["bytes_out"] += await self._forward(evaluator, sid, labels)
            self.sessions.add(sid, bits)
            record["bytes_out"] += conn.write(messages.make("done", sid=sid))
        except ProtocolError as exc:
            record.update(outcome=exc.code, reason=exc.message)
            conn.post(messages.error(exc.code, exc.message, sid))
            if started:
                raise
        except (ConnectionClosed, RemoteError, TimeoutError) as exc:
            record.update(outcome=PEER_LOST, reason=str(exc))
            raise
        finally:
            record["seconds"] = time.monotonic() - t0
            self.finish(slot, record)

    async def _locate(self, msg: dict[str, Any]) -> tuple[Address, Connection]:
        """The link to the evaluator replica the garbler named, if this map owner's
        --evaluator names reach it (ProtocolError ``forbidden`` otherwise)."""
        if not self.evaluator_names:
            raise ProtocolError(FORBIDDEN, "field 'evaluator': this map owner dials no "
                                           "evaluator; its operator must allow one "
                                           "(--evaluator on snail-mapd)")
        return await self.evaluator_names.locate(msg["evaluator"], msg.get("evaluator_id"),
                                         "evaluator", self._evaluator, lambda *_: None)

    async def _forward(self, evaluator: tuple[Address, Connection], sid: bytes,
                       labels: np.ndarray) -> int:
        """Send the evaluator the labels of session ``sid``; the bytes sent."""
        addr, link = evaluator
        try:
            sent = write_labels(link, "owner_labels", sid, labels)
            await link.drain()
        except ConnectionClosed as exc:
            raise ProtocolError(PEER_LOST, f"the map owner cannot reach the evaluator at "
                                           f"{format_addr(*addr)}: {exc}") from None
        return sent

    async def _evaluator(self, addr: tuple[str, int]) -> Connection:
        """The link to the evaluator at ``addr`` (one, reused; reopened when it broke)."""
        lock = self._dialing.setdefault(addr, asyncio.Lock())
        async with lock:
            link = self.evaluators.get(addr)
            if link is None or link.ended or link.peer_closed():
                link = await connect(*addr, self.client_ctx, "mapowner", "evaluator",
                                     self.options.handshake_timeout,
                                     server_name=self.evaluator_names.server_name(addr))
                self.evaluators[addr] = link
                task = asyncio.get_running_loop().create_task(self._listen(link))
                self._tasks.add(task)
                task.add_done_callback(self._tasks.discard)
            return link

    async def _listen(self, link: Connection) -> None:
        """Read what an evaluator says on its link (errors for sessions that failed), so
        its messages never pile up unread."""
        try:
            while True:
                msg, _ = await link.recv()
                if msg["t"] == "error":
                    event(self.log, "evaluator_error", logging.WARNING, code=msg["code"],
                          reason=msg["message"], sid=msg.get("sid", b""))
        except (ConnectionClosed, ProtocolError):
            return

    async def shutdown_extra(self) -> None:
        await asyncio.gather(*(c.close(messages.make("bye")) for c in self.evaluators.values()),
                             return_exceptions=True)
        self.evaluators.clear()
