"""The device's per-run word with the map owner: each map-owner session's pad correction.

A map-owner session's OT ran as it was garbled, ahead of its run, with random bits r as
the map owner's choices (snail_mapd/pads.py). When the device runs it for a frame, once
the garbler has answered for the session (so after that OT), it asks the map owner for
that frame's pads P XOR r, once per session, and XORs it into its own share: xyz ^ P
becomes xyz ^ r, which the circuit XORs with the map owner's r (free) as it did with P.
The device learns P ^ r, a one-time pad of P under r that only the map owner knows, so
nothing of a point. One link per map owner, on the runner's event loop, answers matched by
sid, so the runs of frames in flight ask at the same time; through the evaluator at
``relay`` when given (relay.py), as the device's selections go.
"""

from __future__ import annotations

import asyncio
import ssl
import time
from collections.abc import Awaitable, Callable

import numpy as np

from snail_common.net import messages
from snail_common.net.conn import Connection, connect, parse_addr
from snail_common.net.errors import ConnectionClosed, ProtocolError, RemoteError
from snail_common.pnp.spec import masked_wires

from .links import ServiceError
from .relay import connect_relayed
from .sessions import Prepared


class OwnerRefused(ServiceError):
    """The map owner refused a run's correction or could not be reached: the run fails
    on the map owner's word, neither server is to blame."""


class PadCorrections:
    """Pad corrections from the map owner at ``address`` (connected on first use, through
    the evaluator at ``relay`` when given)."""

    def __init__(self, address: str, ctx: ssl.SSLContext, connect_timeout: float,
                 timeout: float, relay: str | None = None) -> None:
        self.address, self.relay = address, relay
        self.host, self.port = parse_addr(address)
        self.ctx, self.connect_timeout, self.timeout = ctx, connect_timeout, timeout
        self._conn: Connection | None = None
        self._opening: asyncio.Lock | None = None
        self._reader: asyncio.Task | None = None
        self._waiting: dict[bytes, asyncio.Future] = {}

    async def correction(self, frame: bytes, sid: bytes, count: int
                         ) -> tuple[np.ndarray, int, int]:
        """The ``count`` bits (bool) to XOR into session ``sid``'s ``world_masked`` wires
        for ``frame``, and the bytes of the request and of its answer; ServiceError
        naming the map owner when it refuses or is lost."""
        conn = await self._link()
        if sid in self._waiting:
            raise OwnerRefused(f"map owner at {self.address}: a second correction asked "
                               f"for one session")
        waiter = self._waiting[sid] = asyncio.get_running_loop().create_future()
        try:
            sent = conn.write(messages.make("pad_correction_request", frame=frame, sid=sid))
            msg, received = await asyncio.wait_for(waiter, self.timeout)
        except asyncio.TimeoutError:
            raise OwnerRefused(f"the map owner at {self.address} gave no pad correction "
                               f"within {self.timeout:g} s") from None
        except ConnectionClosed as exc:
            raise OwnerRefused(f"lost the map owner at {self.address}: {exc}") from None
        finally:
            self._waiting.pop(sid, None)
        if msg["t"] == "error":
            raise OwnerRefused(f"map owner at {self.address}: {msg['message']}", msg["code"])
        bits = np.unpackbits(np.frombuffer(msg["correction"], np.uint8),
                             bitorder="little").astype(bool)
        if bits.size < count or bits[count:].any():
            raise OwnerRefused(f"map owner at {self.address}: a pad correction of "
                               f"{bits.size} bits for a session of {count}")
        return bits[:count], sent, received

    async def _link(self) -> Connection:
        if self._opening is None:
            self._opening = asyncio.Lock()
        async with self._opening:
            if self._conn is None or self._conn.ended:
                try:
                    self._conn = await (
                        connect(self.host, self.port, self.ctx, "client", "mapowner",
                                self.connect_timeout) if self.relay is None else
                        connect_relayed(self.relay, self.address, self.ctx,
                                        self.connect_timeout))
                except (ConnectionClosed, ProtocolError, RemoteError, TimeoutError, OSError) as exc:
                    raise OwnerRefused(f"cannot reach the map owner at {self.address}: "
                                       f"{exc}") from None
                self._reader = asyncio.get_running_loop().create_task(
                    self._read(self._conn))
            return self._conn

    async def _read(self, conn: Connection) -> None:
        """Hand each answer to the run waiting for its sid; a lost link fails them all."""
        try:
            while True:
                msg, size = await conn.recv()
                waiter = self._waiting.get(msg.get("sid", b""))
                if msg["t"] in ("pad_correction", "error") and waiter is not None \
                        and not waiter.done():
                    waiter.set_result((msg, size))
        except (ConnectionClosed, ProtocolError) as exc:
            for waiter in self._waiting.values():
                if not waiter.done():
                    waiter.set_exception(ConnectionClosed(str(exc)))

    async def close(self) -> None:
        if self._reader is not None:
            self._reader.cancel()
        if self._conn is not None and not self._conn.ended:
            await self._conn.close(messages.make("bye"))


class OwnerInputs:
    """A runner's map-owner side: the frame its map-owner runs take unless they name
    their own, and the pad corrections of each run, asked of the map owner its session
    was garbled for (one link per map owner and relay, all closed with the runner)."""

    def __init__(self, ctx: ssl.SSLContext, connect_timeout: float, timeout: float) -> None:
        self.ctx, self.connect_timeout, self.timeout = ctx, connect_timeout, timeout
        self.frame: tuple[bytes, str] | None = None  # (handle, map owner's address)
        self.relay: str | None = None
        self.used = 0  # corrections received
        self.precomputed = 0  # runs whose session (and OT) was done before the run began
        self.seconds = 0.0  # the runs' time waiting for their corrections
        self._links: dict[tuple[str, str | None], PadCorrections] = {}

    def use(self, handle: bytes, map_owner: str, relay: str | None = None) -> None:
        """Runs from now on take this frame (its handle, its map owner's address) unless
        they name their own; the map owner is reached through ``relay`` when given."""
        self.frame, self.relay = (handle, map_owner), relay

    async def corrected(self, session: Prepared, bits: np.ndarray, frame: bytes | None,
                        garbler_failed: Callable[[], Awaitable[object]]
                        ) -> tuple[np.ndarray, dict[str, int]]:
        """``bits`` with the pad correction of ``session`` for ``frame`` (default: the
        one ``use`` named) folded into its ``world_masked`` share, and the bytes it took
        each way on the link with the map owner; asked once the garbler
        has answered for the session: after its OT with the map owner, so the map owner
        holds its bits; a garbler that refused it (a map owner its operator did not
        allow, say) is heard first: ``garbler_failed`` raises its error."""
        self.precomputed += not session.to_g.empty  # garbled, its OT done, before the run
        await asyncio.wait_for(session.to_g.answered(), self.timeout)
        if session.to_g.failed:
            await garbler_failed()
        t0 = time.perf_counter()
        key = (session.map_owner, self.relay)
        if key not in self._links:
            self._links[key] = PadCorrections(session.map_owner, self.ctx,
                                              self.connect_timeout, self.timeout, self.relay)
        wires = masked_wires(session.iface)
        correction, sent, received = await self._links[key].correction(
            frame or self.frame[0], session.sid, wires.stop - wires.start)
        out = bits.copy()
        out[wires] ^= correction  # OwnerRefused: the map owner's word
        self.used += 1
        self.seconds += time.perf_counter() - t0
        return out, {"client_to_mapowner": sent, "mapowner_to_client": received}

    async def close(self) -> None:
        await asyncio.gather(*(link.close() for link in self._links.values()),
                             return_exceptions=True)
