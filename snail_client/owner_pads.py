"""The device's per-run word with the map owner: each map-owner session's pad correction.

A map-owner session's OT ran as it was garbled, ahead of its run, with random bits r as
the map owner's choices (snail_mapd/pads.py). When the device runs it for a frame, once
the garbler has answered for the session (so after that OT), it asks the map owner for
that frame's pads P XOR r, once per session, and XORs it into its own share: xyz ^ P
becomes xyz ^ r, which the circuit XORs with the map owner's r (free) as it did with P.
The device learns P ^ r, a one-time pad of P under r that only the map owner knows, so
nothing of a point. One link per runner, on the runner's event loop, answers matched by
sid, so the runs of frames in flight ask at the same time; through the evaluator at
``relay`` when given (relay.py), as the device's selections go.
"""

from __future__ import annotations

import asyncio
import ssl
import time

import numpy as np

from snail_common.net import messages
from snail_common.net.conn import Connection, connect, parse_addr
from snail_common.net.errors import ConnectionClosed, ProtocolError, RemoteError

from .links import ServiceError
from .relay import connect_relayed


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
        self.used = 0  # corrections received
        self.precomputed = 0  # runs whose session (and OT) was done before the run began
        self.seconds = 0.0  # the runs' time waiting for their corrections
        self._conn: Connection | None = None
        self._opening: asyncio.Lock | None = None
        self._reader: asyncio.Task | None = None
        self._waiting: dict[bytes, asyncio.Future] = {}

    @property
    def traffic(self) -> dict[str, int]:
        conn = self._conn
        return {"client_to_mapowner": conn.bytes_out if conn else 0,
                "mapowner_to_client": conn.bytes_in if conn else 0}

    async def correction(self, frame: bytes, sid: bytes, count: int) -> np.ndarray:
        """The ``count`` bits (bool) to XOR into session ``sid``'s ``world_masked`` wires
        for ``frame``; ServiceError naming the map owner when it refuses or is lost."""
        t0 = time.perf_counter()
        conn = await self._link()
        if sid in self._waiting:
            raise OwnerRefused(f"map owner at {self.address}: a second correction asked "
                               f"for one session")
        waiter = self._waiting[sid] = asyncio.get_running_loop().create_future()
        try:
            conn.write(messages.make("pad_correction_request", frame=frame, sid=sid))
            msg = await asyncio.wait_for(waiter, self.timeout)
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
        self.used += 1
        self.seconds += time.perf_counter() - t0
        return bits[:count]

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
                msg, _ = await conn.recv()
                waiter = self._waiting.get(msg.get("sid", b""))
                if msg["t"] in ("pad_correction", "error") and waiter is not None \
                        and not waiter.done():
                    waiter.set_result(msg)
        except (ConnectionClosed, ProtocolError) as exc:
            for waiter in self._waiting.values():
                if not waiter.done():
                    waiter.set_exception(ConnectionClosed(str(exc)))

    async def close(self) -> None:
        if self._reader is not None:
            self._reader.cancel()
        if self._conn is not None and not self._conn.ended:
            await self._conn.close(messages.make("bye"))
