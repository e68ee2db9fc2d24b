"""The device's way to its map owner through the evaluator (``--relay``), so that the map
owner never learns the device's network address.

``connect_relayed`` opens a TLS control connection to the evaluator (as role ``client``),
sends ``relay_open`` {map_owner} and waits for ``relay_ready`` (the evaluator dials only
map owners its operator allowed: snail_evaluator/relay.py). Then it makes a socket pair:
one end is pumped to and from the control connection (each read of at most RELAY_DATA
bytes becomes one ``relay_data`` frame, each frame's payload is written to the socket),
and the device's usual TLS client connection to the map owner runs over the other end,
certificates checked end to end as on a direct link. The evaluator sees only those TLS
records. Both directions wait for their writes to drain, so nothing buffers without bound.

The connection it returns behaves as a direct one (mapowner.py and owner_pads.py use it
unchanged); closing it closes the relay, and a relay the evaluator ends (the map owner
gone, the evaluator stopping) ends it with the evaluator's word.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import ssl

from snail_common.net import messages
from snail_common.net.conn import Connection, connect, format_addr, parse_addr
from snail_common.net.errors import (
    UNEXPECTED,
    ConnectionClosed,
    ProtocolError,
    RemoteError,
)
from snail_common.net.frames import MAX_FRAME
from snail_common.net.messages import RELAY_DATA

EVALUATOR = "evaluator"  # --relay with no address: the evaluator the runs go to


class Relay:
    """The device's end of one relay: the control connection to the evaluator and the
    socket whose other end carries the TLS connection to the map owner."""

    def __init__(self, control: Connection, sock: socket.socket, where: str) -> None:
        self.control, self.sock, self.where = control, sock, where
        self.conn: RelayedConnection | None = None  # the map owner's, once made
        self._task = asyncio.get_running_loop().create_task(self._pump())

    async def _pump(self) -> None:
        """Both directions until one ends; then the socket and the control connection
        close (the evaluator's reason, if it gave one, ends the map owner's link)."""
        tasks = [asyncio.ensure_future(self._up()), asyncio.ensure_future(self._down())]
        reason = ""
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            reason = next(iter(done)).result()
        except (ConnectionClosed, ProtocolError, OSError) as exc:
            reason = f"the relay at {self.where} failed: {exc}"
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            if reason and self.conn is not None:
                self.conn.relay_ended(reason)
            self.sock.close()
            await self.control.close(messages.make("bye"))

    async def _up(self) -> str:
        """The TLS bytes the device writes, to the evaluator."""
        loop = asyncio.get_running_loop()
        while True:
            data = await loop.sock_recv(self.sock, RELAY_DATA)
            if not data:
                return ""
            await self.control.send(messages.make("relay_data", data=data))

    async def _down(self) -> str:
        """The map owner's TLS bytes from the evaluator, to the device; the evaluator's
        error, if it ends the relay with one."""
        loop = asyncio.get_running_loop()
        while True:
            msg, _ = await self.control.recv()
            kind = msg["t"]
            if kind == "bye":
                return ""
            if kind == "error":
                return f"the relay at {self.where} ended: {msg['code']}: {msg['message']}"
            if kind != "relay_data":
                raise ProtocolError(UNEXPECTED, f"the evaluator sent {kind} on a relay")
            await loop.sock_sendall(self.sock, msg["data"])

    async def close(self, timeout: float = 2.0) -> None:
        """Wait until the pump has passed on the last bytes of the map owner's link (closed
        already: its socket reads EOF once they are out) and closed the relay; cut it
        after ``timeout`` (an evaluator that stopped reading)."""
        try:
            await asyncio.wait_for(asyncio.shield(self._task), timeout)
        except asyncio.TimeoutError:
            self.abort()
        await asyncio.gather(self._task, return_exceptions=True)

    def abort(self) -> None:
        """Cut the relay now: the socket reads EOF (closing it under a pending read would
        leave that read to the event loop's mercy), the control connection is dropped."""
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.control.abort()
        self._task.cancel()


class RelayedConnection(Connection):
    """A connection to the map owner that runs over a relay: closing it closes the
    relay too."""

    def __init__(self, relay: Relay, max_frame: int = MAX_FRAME) -> None:
        super().__init__(max_frame)
        self.relay = relay
        relay.conn = self

    def relay_ended(self, reason: str) -> None:
        """The relay ended under this connection: its reader hears ``reason``."""
        self._end(ConnectionClosed(reason))

    async def close(self, last: dict | None = None, timeout: float = 2.0) -> None:
        await super().close(last, timeout)
        await self.relay.close()

    def abort(self) -> None:
        super().abort()
        self.relay.abort()


async def connect_relayed(relay: str, map_owner: str, ctx: ssl.SSLContext,
                          timeout: float, server_name: str | None = None) -> Connection:
    """A client's TLS connection to the map owner at ``map_owner`` through the evaluator
    at ``relay``, which must present the evaluator's certificate, and the map owner the
    map owner's naming ``server_name`` (default: its host). ConnectionClosed when either
    cannot be reached, RemoteError when the evaluator refuses the relay (``forbidden``:
    a map owner its operator did not allow); ValueError for an address not HOST:PORT."""
    host, port = parse_addr(relay)
    owner_host, owner_port = parse_addr(map_owner)
    where = format_addr(host, port)
    control = await connect(host, port, ctx, "client", "evaluator", timeout)
    try:
        control.write(messages.make("relay_open", map_owner=map_owner))
        await control.expect("relay_ready", timeout)
    except RemoteError as exc:
        control.abort()
        raise RemoteError(exc.code, f"the relay at {where}: {exc.message}") from None
    except (ConnectionClosed, ProtocolError, TimeoutError) as exc:
        control.abort()
        raise ConnectionClosed(f"the relay at {where}: {exc}") from None
    except BaseException:
        control.abort()
        raise
    ours, theirs = socket.socketpair()
    ours.setblocking(False)
    pumped = Relay(control, ours, where)
    try:  # the socket is the TLS transport's from here on: it closes it
        return await connect(owner_host, owner_port, ctx, "client", "mapowner", timeout,
                             server_name=server_name, sock=theirs,
                             factory=lambda: RelayedConnection(pumped))
    except ConnectionClosed as exc:
        pumped.abort()
        raise ConnectionClosed(f"{exc} (through the relay at {where})") from None
    except BaseException:
        pumped.abort()
        raise
