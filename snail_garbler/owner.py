"""The map owner's input wires of a session: the garbler is the sender of a chosen-message
IKNP OT whose receiver is the map owner (snail-mapd).

For a circuit whose last input group is the map owner's (``pnp.spec.owner_bits``), the
client's ``garble_request`` names the map owner's address. The garbler derives those
wires' zero-labels L0 from the client's seed, as for every input, and offers (L0, L0 ^ D)
per wire as the session is garbled, ahead of its run; the map owner's choices are fresh
random bits r of that session, so it gets one label per wire and never D, and forwards
them to the evaluator. No frame is named here: when the device runs the session for a
frame, the map owner tells the device the frame's pad bits XOR r (the derandomization of
a random OT, as Beaver's), which the device folds into its own share of the points; the
circuit XORs the two shares as before. So this OT is off the run's path, and a session
garbled ahead serves whichever frame comes. The garbler learns nothing of r (IKNP hides
the choices). Links are kept per map-owner address with their OT state: the base OTs
(~0.1 s) run once per link, not per session.

The client names the address, so the garbler dials only map owners its operator allowed
(``--map-owner``, names resolved: snail_common.net.replicas): otherwise any client could
make it open connections to any host and port (a server-side request forgery). A request
naming another address is refused (``forbidden``) before any connection is made; with
none allowed, every map-owner session is. The map owner forwards the labels to the
evaluator replica this session streams to, which the garbler names by address and
instance id; the map owner checks it against its own operator's ``--evaluator``.
"""

from __future__ import annotations

import asyncio
import ssl
from collections.abc import Iterable
from typing import Any

import numpy as np

from snail_common.circuit.ir import FIRST_INPUT, Circuit
from snail_common.gc import derive_zero_labels, labels_from_bytes
from snail_common.net import messages
from snail_common.net.conn import Connection, connect
from snail_common.net.errors import (
    BAD_REQUEST,
    FORBIDDEN,
    PEER_LOST,
    UNEXPECTED,
    ConnectionClosed,
    ProtocolError,
    RemoteError,
)
from snail_common.net.replicas import Replicas
from snail_common.ot import ExtSender
from snail_common.ot.carry import ot_part
from snail_common.pnp.spec import owner_bits

MAX_IDLE = 8  # idle links kept per map owner

Link = tuple[Connection, ExtSender]
NOT_ALLOWED = "the operator must allow it (--map-owner on the garbler)"


class OwnerInputs:
    """Runs the OT of the map owner's wires for a session; pools the links."""

    def __init__(self, ctx: ssl.SSLContext, handshake_timeout: float,
                 allowed: Iterable[tuple[str, int]]) -> None:
        self.ctx = ctx
        self.allowed = Replicas(allowed, "--map-owner", "map owner")
        self.handshake_timeout = handshake_timeout
        self.idle: dict[tuple[str, int], list[Link]] = {}

    async def feed(self, req: dict[str, Any], circuit: Circuit, timeout: float,
                   evaluator: tuple[str, str | None]) -> dict[str, int]:
        """Give the map owner its labels for session ``req`` (nothing to do for a circuit
        without map-owner wires), to forward to ``evaluator`` (the replica's address as
        this garbler reached it, and its instance id); the bytes each way. ProtocolError
        for a request that does not fit the circuit, a map owner the operator did not
        allow (``forbidden``), the map owner's refusal or a lost map owner."""
        count = owner_bits(circuit)
        if not count:
            if "map_owner" in req:
                raise ProtocolError(BAD_REQUEST, f"field 'map_owner': circuit "
                                                 f"{req['circuit']} takes no map-owner input")
            return {}
        if "map_owner" not in req:
            raise ProtocolError(BAD_REQUEST, f"circuit {req['circuit']} takes the map "
                                             f"owner's input: 'map_owner' is required")
        if not self.allowed:
            raise ProtocolError(FORBIDDEN, f"field 'map_owner': this garbler dials no map "
                                           f"owner, none is allowed; {NOT_ALLOWED}")
        addr = await self.allowed.check(req["map_owner"], "map_owner")
        x0 = derive_zero_labels(req["seed"], FIRST_INPUT + circuit.n_inputs)[-count:]
        x1 = x0 ^ labels_from_bytes(req["delta"])[0]
        conn, ot = await self._acquire(addr)
        before = conn.bytes_out, conn.bytes_in
        try:
            await self._run(conn, ot, req, count, x0, x1, timeout, evaluator)
        except RemoteError as exc:  # the client hears it as the map owner's, not the evaluator's
            conn.abort()
            raise ProtocolError(exc.code, exc.message) from None
        except ConnectionClosed as exc:
            conn.abort()
            raise ProtocolError(PEER_LOST, f"lost the map owner: {exc}") from None
        except BaseException:
            conn.abort()
            raise
        self._release(addr, (conn, ot))
        return {"garbler_to_mapowner": conn.bytes_out - before[0],
                "mapowner_to_garbler": conn.bytes_in - before[1]}

    async def _run(self, conn: Connection, ot: ExtSender, req: dict[str, Any], count: int,
                   x0: np.ndarray, x1: np.ndarray, timeout: float,
                   evaluator: tuple[str, str | None]) -> None:
        sid, (address, instance) = req["sid"], evaluator
        extra = {"evaluator_id": instance} if instance is not None else {}
        conn.write(messages.make("map_invocation", sid=sid, count=count, evaluator=address,
                                 **extra))
        while True:
            msg, _ = await conn.recv(timeout)
            kind = msg["t"]
            if kind == "error":
                raise RemoteError(msg["code"], f"the map owner reported: {msg['message']}",
                                  msg.get("sid"))
            if kind == "ot_base_a":
                conn.write(messages.make("ot_base_b", b=ot.base_reply(ot_part(msg))["b"]))
            elif kind == "ot_ext_u" and msg.get("sid") == sid:
                answer = ot.respond_chosen(ot_part(msg), x0, x1)
                conn.write(messages.make("ot_ext_y", sid=sid, start=answer["start"],
                                         y=answer["y"]))
            elif kind == "done" and msg["sid"] == sid:
                return
            else:
                raise ProtocolError(UNEXPECTED, f"the map owner sent {kind} mid-invocation")

    async def _acquire(self, addr: tuple[str, int]) -> Link:
        pool = self.idle.get(addr, [])
        while pool:
            conn, ot = pool.pop()
            if conn.idle:
                return conn, ot
            conn.abort()
        try:
            conn = await connect(*addr, self.ctx, "garbler", "mapowner",
                                 self.handshake_timeout,
                                 server_name=self.allowed.server_name(addr))
        except ConnectionClosed as exc:
            raise ProtocolError(PEER_LOST, f"cannot reach the map owner: {exc}") from None
        return conn, ExtSender()

    def _release(self, addr: tuple[str, int], link: Link) -> None:
        pool = self.idle.setdefault(addr, [])
        if link[0].idle and len(pool) < MAX_IDLE:
            pool.append(link)
        else:
            link[0].abort()

    async def close(self) -> None:
        links = [conn for pool in self.idle.values() for conn, _ in pool]
        self.idle.clear()
        await asyncio.gather(*(c.close(messages.make("bye")) for c in links),
                             return_exceptions=True)
