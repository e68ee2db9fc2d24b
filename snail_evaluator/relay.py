"""The evaluator as a relay between a device and its map owner (the map-owner setting).

A device that dials the map owner itself tells it its network address and when it
localizes. Through the relay the map owner sees the evaluator's address instead; the
device's TLS connection to the map owner runs end to end inside it (snail_client/relay.py),
so the evaluator carries records it can neither read nor change unnoticed: the device
checks the map owner's certificate and the map owner the device's, as on a direct link.

A client connection whose first message is ``relay_open`` {map_owner} is a relay and
carries nothing else. The address must be one this evaluator's operator allowed
(``--map-owner``, names resolved as the garbler's are: snail_common.net.replicas), else
the device hears ``forbidden`` and nothing is dialled: a client must not make the
evaluator connect where it likes. The evaluator then opens a plain TCP connection to the
map owner (within ``--handshake-timeout``) and answers ``relay_ready``, or an ``error``
naming the map owner it could not reach. From then on it pumps bytes: each
``relay_data`` payload is written to the map owner (awaiting the socket's drain), each read
from the map owner (at most RELAY_DATA bytes) goes to the device as one ``relay_data``
(awaiting the TLS link's drain); the device's link reads a few frames ahead at most, so a
relay holds at most a few hundred KiB either way and backpressure reaches both ends.
Either end closing (the device's ``bye`` or close, the map owner's EOF) closes the other;
a relay with nothing moving either way for ``--idle-timeout`` is closed. Each relay logs
one ``relay`` line: the map owner, the bytes each way, its seconds and its outcome.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass, field

from snail_common.net import messages
from snail_common.net.conn import Connection, format_addr
from snail_common.net.dial import dial_tcp
from snail_common.net.errors import (
    FORBIDDEN,
    PEER_LOST,
    SHUTDOWN,
    TIMEOUT,
    UNEXPECTED,
    ConnectionClosed,
    ProtocolError,
)
from snail_common.net.logs import event
from snail_common.net.messages import RELAY_DATA
from snail_common.net.metrics import OK
from snail_common.net.replicas import Address, Replicas

NOT_ALLOWED = "the operator must allow it (--map-owner on the evaluator)"


@dataclass
class _Pumped:
    """What one relay moved, and when last."""

    to_owner: int = 0
    to_device: int = 0
    moved: float = field(default_factory=time.monotonic)

    def add(self, owner: int = 0, device: int = 0) -> None:
        self.to_owner += owner
        self.to_device += device
        self.moved = time.monotonic()


class Relays:
    """The relays of one evaluator, to the map owners its operator allowed."""

    def __init__(self, map_owners: Iterable[Address], connect_timeout: float,
                 idle_timeout: float, logger: logging.Logger) -> None:
        self.allowed = Replicas(map_owners, "--map-owner", "map owner")
        self.connect_timeout, self.idle_timeout = connect_timeout, idle_timeout
        self.log = logger

    async def serve(self, conn: Connection, request: dict) -> None:
        """Relay ``conn`` (whose first message was ``request``, a ``relay_open``) to the
        map owner it names until either end closes; the device hears any failure."""
        began, pumped = time.monotonic(), _Pumped()
        named, outcome, reason, last = request["map_owner"], OK, "", messages.make("bye")
        try:
            reader, writer = await self._open(named)
        except ProtocolError as exc:
            self._logged(conn, named, pumped, began, exc.code, exc.message)
            await conn.close(messages.error(exc.code, exc.message))
            return
        try:
            conn.write(messages.make("relay_ready"))
            ended = await _first([self._to_owner(conn, writer, pumped, named),
                                  self._to_device(conn, reader, pumped, named)])
            reason = f"closed by the {ended}"
        except ProtocolError as exc:
            outcome, reason, last = exc.code, exc.message, messages.error(exc.code,
                                                                           exc.message)
        except ConnectionClosed as exc:  # the device's link broke: nobody to tell
            reason = str(exc)
        except asyncio.CancelledError:  # the evaluator is stopping: its close ends it
            outcome, reason = SHUTDOWN, "the evaluator stopped"
            raise
        finally:
            writer.close()
            self._logged(conn, named, pumped, began, outcome, reason)
        await conn.close(last)

    async def _open(self, named: str) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        """A TCP connection to the map owner ``named``, if the operator allowed it:
        ProtocolError (forbidden before any dial, peer_lost naming it unreachable)."""
        if not self.allowed:
            raise ProtocolError(FORBIDDEN, f"field 'map_owner': this evaluator relays to no "
                                           f"map owner, none is allowed; {NOT_ALLOWED}")
        host, port = await self.allowed.check(named, "map_owner")
        try:
            return await asyncio.wait_for(_dial(host, port), self.connect_timeout)
        except (OSError, asyncio.TimeoutError) as exc:
            why = str(exc) or f"no connection within {self.connect_timeout:g} s"
            raise ProtocolError(PEER_LOST, f"cannot reach the map owner at "
                                           f"{format_addr(host, port)}: {why}") from None

    async def _to_owner(self, conn: Connection, writer: asyncio.StreamWriter,
                        pumped: _Pumped, named: str) -> str:
        """The device's relay_data payloads to the map owner, until the device's bye or
        close; ProtocolError for any other message, or a relay idle too long."""
        while True:
            try:
                msg, _ = await conn.recv(self.idle_timeout)
            except TimeoutError:
                if time.monotonic() - pumped.moved < self.idle_timeout:
                    continue
                raise ProtocolError(TIMEOUT, f"the relay was idle for "
                                             f"{self.idle_timeout:g} s") from None
            except ConnectionClosed:
                return "device"
            if msg["t"] == "bye":
                return "device"
            if msg["t"] != "relay_data":
                raise ProtocolError(UNEXPECTED, f"a relayed connection carries relay_data "
                                                f"only, not {msg['t']}")
            try:
                writer.write(msg["data"])
                await writer.drain()
            except OSError as exc:
                raise ProtocolError(PEER_LOST, f"lost the map owner at {named}: "
                                               f"{exc}") from None
            pumped.add(owner=len(msg["data"]))

    @staticmethod
    async def _to_device(conn: Connection, reader: asyncio.StreamReader, pumped: _Pumped,
                         named: str) -> str:
        """What the map owner sends, to the device in relay_data frames, until its EOF;
        ProtocolError (peer_lost) when its connection breaks."""
        while True:
            try:
                data = await reader.read(RELAY_DATA)
            except OSError as exc:
                raise ProtocolError(PEER_LOST, f"lost the map owner at {named}: "
                                               f"{exc}") from None
            if not data:
                return "map owner"
            await conn.send(messages.make("relay_data", data=data))
            pumped.add(device=len(data))

    def _logged(self, conn: Connection, named: str, pumped: _Pumped, began: float,
                outcome: str, reason: str) -> None:
        event(self.log, "relay", logging.INFO if outcome == OK else logging.WARNING,
              peer=conn.peer_name, map_owner=named, bytes_to_owner=pumped.to_owner,
              bytes_to_device=pumped.to_device,
              seconds=round(time.monotonic() - began, 4), outcome=outcome,
              **({"reason": reason} if reason else {}))


async def _first(pumps: list) -> str:
    """Run both directions until one ends: its result (or its error); the other is
    cancelled."""
    tasks = [asyncio.ensure_future(p) for p in pumps]
    try:
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        return next(iter(done)).result()
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)


async def _dial(host: str, port: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """Streams over a TCP connection to ``host``, dialled for small bursts (a device's
    link: snail_common/net/dial.py)."""
    return await asyncio.open_connection(sock=await dial_tcp(host, port), limit=RELAY_DATA)
