"""The device's link to a map owner (snail-mapd): the published map, then one oblivious
selection per frame.

The device is the receiver of the selection's OTs (its index bits are the choices; base
OTs once per link). Per frame it gets xyz ^ P for its map points, P being pads only the
map owner holds, and a frame handle that the garbler later names to the map owner for the
iteration circuits' pad inputs. Nothing the device sends carries a 2D point, a pose or an
id in the clear; nothing it receives carries a 3D point in the clear. With a ``relay``
(an evaluator's address) the link runs through it (relay.py): the map owner sees the
evaluator's address, not the device's.
"""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path

import numpy as np

from snail_common.loc.owner import POINT_BYTES, PublishedMap
from snail_common.net import messages, tls
from snail_common.net.conn import Connection, connect, new_event_loop, parse_addr
from snail_common.net.errors import ConnectionClosed, ProtocolError, RemoteError
from snail_common.ot import ExtReceiver
from snail_common.ot.carry import BlobAssembler, as_words, ot_part
from snail_common.ot.selection import MAX_TABLE_BYTES, SelectReceiver

from .links import ServiceError
from .relay import connect_relayed

DEFAULT_TIMEOUT = 120.0


class MapOwnerLink:
    """A blocking link to the map owner at ``address`` (its own event loop), through the
    evaluator at ``relay`` when given."""

    def __init__(self, address: str, tls_dir: str | Path, cert_name: str = "client",
                 timeout: float = DEFAULT_TIMEOUT, relay: str | None = None) -> None:
        try:
            self.host, self.port = parse_addr(address)
        except ValueError as exc:
            raise ValueError(f"--map-owner: {exc}") from None
        if relay is not None:
            try:
                parse_addr(relay)
            except ValueError as exc:
                raise ValueError(f"--relay: {exc}") from None
        self.address, self.relay = address, relay
        self.ctx = tls.client_context(tls_dir, "client", cert_name)
        self.timeout = timeout
        self.published: PublishedMap | None = None
        self._loop = new_event_loop()
        self._lock = threading.Lock()  # frames in flight select from their own threads
        self._conn: Connection | None = None
        self._ot: ExtReceiver | None = None
        self.selections, self.select_s = 0, 0.0  # frames selected, their wall time

    @property
    def traffic(self) -> dict[str, int]:
        conn = self._conn
        return {"client_to_mapowner": conn.bytes_out if conn else 0,
                "mapowner_to_client": conn.bytes_in if conn else 0}

    def open(self) -> PublishedMap:
        """Connect, read the published map and run the base OTs."""
        self.published = self._call(self._open())
        return self.published

    def select(self, map_ids: np.ndarray) -> tuple[bytes, np.ndarray]:
        """(frame handle, (n, 3) uint32 words of xyz ^ P) for the frame's map ids;
        ProblemError naming an id that is not in the map."""
        if self.published is None:
            self.open()
        positions = self.published.positions(np.asarray(map_ids, np.int64))
        t0 = time.perf_counter()
        selected = self._call(self._select(positions))
        self.selections += 1
        self.select_s += time.perf_counter() - t0
        return selected

    def _call(self, coro) -> object:
        try:
            with self._lock:
                return self._loop.run_until_complete(asyncio.wait_for(coro, self.timeout))
        except asyncio.TimeoutError:
            raise ServiceError(f"the map owner at {self.address} did not answer within "
                               f"{self.timeout:g} s") from None
        except (ConnectionClosed, ProtocolError, RemoteError, TimeoutError) as exc:
            raise ServiceError(f"map owner at {self.address}: {exc}") from None

    async def _open(self) -> PublishedMap:
        conn = self._conn = await (
            connect(self.host, self.port, self.ctx, "client", "mapowner", self.timeout)
            if self.relay is None else
            connect_relayed(self.relay, self.address, self.ctx, self.timeout))
        conn.write(messages.make("map_info_request"))
        msg = await conn.expect("map_info")
        first, parts, have = msg, [msg["ids"]], len(msg["ids"]) // 4
        while have < first["points"]:
            msg = await conn.expect("map_info")
            if msg["start"] != have or msg["points"] != first["points"]:
                raise ProtocolError("bad_request", "map_info chunks out of order")
            parts.append(msg["ids"])
            have += len(msg["ids"]) // 4
        try:
            published = PublishedMap.from_wire(b"".join(parts), first["transform"])
        except ValueError as exc:
            raise ProtocolError("bad_request", str(exc)) from None
        ot = ExtReceiver()
        conn.write(messages.make("ot_base_a", a=ot.start()["a"]))
        ot.base_done(ot_part(await conn.expect("ot_base_b")))
        self._ot = ot
        return published

    async def _select(self, positions: np.ndarray) -> tuple[bytes, np.ndarray]:
        conn = self._conn
        receiver = SelectReceiver(self._ot, len(self.published.ids), POINT_BYTES)
        request = receiver.request(positions)
        conn.write(messages.make("ot_ext_u", start=request["start"], m=request["m"],
                                 u=request["u"]))
        msg = await conn.expect("sel_table")
        head = (msg["frame"], msg["start"], msg["key"])
        table = BlobAssembler("sel_table", msg["total"], MAX_TABLE_BYTES)
        table.add(msg["offset"], msg["table"])
        while not table.complete:
            msg = await conn.expect("sel_table")
            if (msg["frame"], msg["start"], msg["key"]) != head:
                raise ProtocolError("bad_request", "sel_table chunks of two selections")
            table.add(msg["offset"], msg["table"])
        rows = receiver.receive({"t": "sel_table", "start": head[1], "key": head[2],
                                 "table": table.data()})
        return head[0], as_words(rows)

    def close(self) -> None:
        if self._loop.is_closed():
            return
        if self._conn is not None:
            self._loop.run_until_complete(self._conn.close(messages.make("bye")))
        self._loop.close()

    def __enter__(self) -> MapOwnerLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
