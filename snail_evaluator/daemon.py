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

The client's half is ``client_side.py``, the garbler's ``tables.py``, a session's state
``session.py``; this module keeps the session book where the halves meet. A client
connection may instead be a relay to a map owner its operator allowed (``relay.py``).
"""

from __future__ import annotations

import asyncio
import logging
import ssl
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from snail_common.gc.stream import DEFAULT_SCHEME
from snail_common.net import messages
from snail_common.net.conn import Connection
from snail_common.net.datalink import TLS, DataPort
from snail_common.net.errors import (
    BAD_REQUEST,
    EVICTED,
    TIMEOUT,
    ConnectionClosed,
    ProtocolError,
)
from snail_common.net.logs import event
from snail_common.net.metrics import OK
from snail_common.net.replicas import Address
from snail_common.net.service import Daemon, Options
from snail_common.net.sharedport import SharedPort

from .client_side import ClientSide
from .lanes import LaneBatcher
from .owner import EarlyOwnerLabels
from .relay import Relays
from .session import Session, consume_failure
from .tables import GarblerSide

ENDED_KEPT = 4096  # sids of ended or refused sessions remembered (remember_ended)


class EvaluatorDaemon(ClientSide, GarblerSide, Daemon):
    role = "evaluator"
    allowed = ("client", "garbler", "mapowner")

    def __init__(self, options: Options, logger: logging.Logger,
                 map_owners: Iterable[Address] = ()) -> None:
        super().__init__(options, logger)
        # the only map owners this evaluator relays devices to (--map-owner)
        self.relays = Relays(map_owners, options.handshake_timeout, options.idle_timeout,
                             logger)
        self.sessions: dict[bytes, Session] = {}
        self.ended: OrderedDict[bytes, ProtocolError] = OrderedDict()  # sid -> why
        self.lanes = LaneBatcher(options.lane_window_ms / 1000, options.max_lanes)
        self.owner_early = EarlyOwnerLabels()
        self.data_port = DataPort(options.table_link, options.handshake_timeout, logger,
                                  self._data_link, self._data_link_refused,
                                  options.session_timeout, self.bodies)

    # ---- the garbler's table data link (snail_common/net/datalink.py) --------------------
    def capabilities_for(self, conn: Connection) -> dict[str, Any]:
        """A garbler's carry how its tables travel (and its token for the data port)."""
        caps = self.capabilities()
        return caps | self.data_port.grant(conn) if conn.peer_role == "garbler" else caps

    async def listen(self, host: str, port: int, ctx: ssl.SSLContext,
                     factory: Callable[[], Connection]) -> Any:
        """With a data link, its connections come to the TLS port (sharedport.py)."""
        if self.options.table_link == TLS:
            return await super().listen(host, port, ctx, factory)
        return await SharedPort(factory, ctx, self.data_port.gate,
                                self.options.handshake_timeout,
                                self._silent).start(host, port)

    def _data_link(self, conn: Connection) -> None:
        """A data link brought its token: confirm it (sealed, in aead) and serve it."""
        try:
            conn.write(self.capabilities())
        except ConnectionClosed:
            return
        self.serve_later(conn)

    def _data_link_refused(self) -> None:
        self.metrics.refused["data_link"] += 1

    def _silent(self, address: str) -> None:
        """A connection to the port that sent nothing within --handshake-timeout."""
        self.metrics.refused["handshake"] += 1
        event(self.log, "connection_rejected", logging.WARNING, address=address,
              reason=f"nothing sent within {self.options.handshake_timeout:g} s")

    @property
    def ahead_buffered(self) -> int:
        """Table bytes held for sessions still awaiting labels (the queued_bytes gauge)."""
        return self.counters["queued_bytes"]

    @ahead_buffered.setter
    def ahead_buffered(self, value: int) -> None:
        self.counters["queued_bytes"] = value

    # ---- session bookkeeping ---------------------------------------------------------------
    def _open(self, msg: dict[str, Any], size: int, peer: str = "") -> Session:
        """A new session from whichever half came first (``peer``: the client's name when
        it is the client's), or ProtocolError (busy, draining). A reservation's
        (``ahead``) place may be taken by a live session: it then fails as evicted."""
        s = Session(msg["sid"], msg["circuit"], msg["hash"],
                    asyncio.get_running_loop().create_future(), peer=peer, bytes_in=size,
                    scheme=msg.get("scheme", DEFAULT_SCHEME))
        s.slot = self.admit(peer, bool(msg.get("ahead")), evict=lambda: self._fail(
            s, ProtocolError(EVICTED, "a live session took the place of this one, garbled "
                                      "ahead (busy evaluator)")))
        s.ready.add_done_callback(consume_failure)
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
        self.remember_ended(s.sid, exc)
        s.failure = exc
        if s.watchdog:
            s.watchdog.cancel()
        if not s.ready.done():
            s.ready.set_exception(exc)
        if s.client is not None:
            s.client.post(messages.error(exc.code, exc.message, s.sid))
        self.finish(s.slot, s.record(exc.code, exc.message))

    def remember_ended(self, sid: bytes, exc: ProtocolError) -> None:
        """A session that failed, or whose client half was refused: a garbler half that
        still comes for it is told at once (tables.py), not held for a client that
        never shows up."""
        self.ended[sid] = ProtocolError(exc.code, exc.message)  # no traceback kept
        while len(self.ended) > ENDED_KEPT:
            self.ended.popitem(last=False)

    def _complete(self, s: Session) -> None:
        del self.sessions[s.sid]
        self.finish(s.slot, s.record(OK))

    def _check_same(self, s: Session, msg: dict[str, Any]) -> None:
        if (msg["circuit"], msg["hash"]) != (s.circuit, s.hash):
            raise ProtocolError(BAD_REQUEST, f"client and garbler disagree on the circuit "
                                             f"of this session ({s.circuit} vs "
                                             f"{msg['circuit']})")
        if msg.get("scheme", DEFAULT_SCHEME) != s.scheme:
            raise ProtocolError(BAD_REQUEST, f"client and garbler disagree on the garbling "
                                             f"scheme of this session ({s.scheme} vs "
                                             f"{msg.get('scheme', DEFAULT_SCHEME)})")

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
            self.slots.live(s.slot)  # in use now: a reservation no more
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

    def finish(self, slot, record: dict) -> None:
        """A session ended: map-owner labels still waiting for it go too."""
        self.owner_early.drop(record["sid"])
        super().finish(slot, record)

