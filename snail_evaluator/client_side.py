"""The client's half of an evaluator session: ``session_start``, its input labels (some
may come before the circuit is loaded, and are replayed once it is) and cancellations.
Mixed into ``EvaluatorDaemon``, whose session book (``daemon.py``) it uses. A connection
that opens with ``relay_open`` is a relay to a map owner instead (``relay.py``)."""

from __future__ import annotations

import asyncio
from typing import Any

from snail_common.circuit.ir import FIRST_INPUT
from snail_common.net import messages
from snail_common.net.chunks import LabelAssembler
from snail_common.net.conn import Connection
from snail_common.net.errors import (
    ABORTED,
    BAD_REQUEST,
    BUSY,
    DRAINING,
    DUPLICATE_SESSION,
    UNEXPECTED,
    ProtocolError,
)
from snail_common.pnp.spec import owner_bits

from .session import MAX_EARLY_LABEL_BYTES, Session


class ClientSide:
    """The evaluator's client connections."""

    async def _serve_client(self, conn: Connection) -> None:
        """A client's messages, each handled at once: a circuit being loaded or compiled
        for a session does not hold up the connection (a client probes a quiet link with
        ``health_request`` and gives it up if unanswered)."""
        loading: set[asyncio.Task] = set()
        first = True
        try:
            while True:
                msg, size = await self.next_message(
                    conn, lambda: any(s.client is conn for s in self.sessions.values()))
                kind = msg["t"]
                if kind == "relay_open":
                    if not first:
                        raise ProtocolError(UNEXPECTED, "relay_open opens a connection of "
                                                        "its own: it must be the first "
                                                        "message after hello")
                    await self.relays.serve(conn, msg)
                    return
                first = False
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
        s = self.sessions.get(sid)
        if s is not None and s.client is not None:
            conn.post(messages.error(DUPLICATE_SESSION, "session id already in use", sid))
            return None
        ended = self.ended.get(sid) if s is None else None
        if ended is not None:  # its garbler half came first and the session has ended
            conn.post(messages.error(ended.code, ended.message, sid))
            return None
        try:
            if s is None:
                s = self._open(msg, size, conn.peer_name)
            else:  # the garbler's half came first
                self._check_same(s, msg)
                self.claim(s.slot, conn.peer_name)
                if not msg.get("ahead"):
                    self.slots.live(s.slot)
                s.peer = conn.peer_name
                s.bytes_in += size
        except ProtocolError as exc:
            conn.post(messages.error(exc.code, exc.message, sid))
            if s is not None:  # its garbler half is told too, and the slot freed
                self._fail(s, exc)
                return None
            self.remember_ended(sid, exc)
            if exc.code in (BUSY, DRAINING):  # refused for want of a slot: one line
                self.log_session(peer=conn.peer_name, sid=sid, circuit=msg["circuit"],
                                 n_and=0, bytes_in=size, bytes_out=0, seconds=0.0,
                                 outcome=exc.code, reason=exc.message)
            return None
        s.client = conn
        s.signer = msg.get("signer")  # the garbler key its tables must verify under
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
