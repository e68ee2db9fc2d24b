"""A TCP proxy on loopback that a test puts on one link and then breaks on purpose.

TLS passes through it untouched (it only moves bytes), so the daemons and the client see
a real network fault: a peer that stops reading (``stall``), a partition that keeps both
sockets open and silent (``partition``), a link cut with a reset (``cut``), a slow link
(``rate``), or one that changes a byte on the way (``flip_in``); with ``hold_closes`` the
proxy's client does not hear its target close the connection until ``release``. It runs
its own event loop in a thread, so tests can drive blocking clients while it misbehaves.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
import threading
from dataclasses import dataclass, field

CHUNK = 16384


@dataclass
class _Pipe:
    """One direction of one proxied connection."""

    reader: asyncio.StreamReader
    writer: asyncio.StreamWriter
    upstream: bool  # from the proxy's client towards its target
    moved: int = 0


@dataclass
class FaultProxy:
    """Forwards 127.0.0.1:``port`` to ``target``; ``mode`` changes what it does now."""

    target: tuple[str, int]
    mode: str = "forward"  # forward | stall | partition
    rate_bytes_per_s: float | None = None
    # this many bytes towards the target from now (over all connections), one bit of the
    # next byte is flipped, once
    flip_in: int | None = None
    # while set, a connection the target closed (or reset) stays open towards the proxy's
    # client, silent, as if the target still held it; ``release`` passes the closes on
    hold_closes: bool = False
    port: int = 0
    bytes_forwarded: int = 0
    _loop: asyncio.AbstractEventLoop = field(default_factory=asyncio.new_event_loop)
    _writers: list[asyncio.StreamWriter] = field(default_factory=list)
    _thread: threading.Thread | None = None
    _held: int = 0  # connections whose close is held now

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.port}"

    def __enter__(self) -> FaultProxy:
        ready = threading.Event()

        def run() -> None:
            asyncio.set_event_loop(self._loop)
            server = self._loop.run_until_complete(
                asyncio.start_server(self._accept, "127.0.0.1", 0))
            self.port = server.sockets[0].getsockname()[1]
            ready.set()
            self._loop.run_forever()
            server.close()
            self._loop.run_until_complete(server.wait_closed())

        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()
        ready.wait(10)
        return self

    def __exit__(self, *exc: object) -> None:
        self.hold_closes = False
        self._loop.call_soon_threadsafe(self._close_all, False)
        self._loop.call_soon_threadsafe(self._loop.stop)
        if self._thread:
            self._thread.join(10)

    def set(self, mode: str, rate_bytes_per_s: float | None = None) -> None:
        """Switch to ``mode`` (forward, stall, partition) for every connection, now."""
        self.mode, self.rate_bytes_per_s = mode, rate_bytes_per_s

    def cut(self) -> None:
        """Reset every proxied connection (RST, not FIN), as a crashed middlebox would."""
        done = threading.Event()
        self._loop.call_soon_threadsafe(lambda: (self._close_all(True), done.set()))
        done.wait(5)

    def release(self) -> None:
        """Pass on the closes held since ``hold_closes`` was set; return once they are."""
        async def passed_on() -> None:
            self.hold_closes = False
            while self._held:
                await asyncio.sleep(0.01)

        asyncio.run_coroutine_threadsafe(passed_on(), self._loop).result(60)

    def _close_all(self, reset: bool) -> None:
        for writer in self._writers:
            sock = writer.get_extra_info("socket")
            if reset and sock is not None:
                with contextlib.suppress(OSError):  # already closed by its peer
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER,
                                    struct.pack("ii", 1, 0))
            writer.close()
        self._writers.clear()

    async def _accept(self, reader: asyncio.StreamReader,
                      writer: asyncio.StreamWriter) -> None:
        try:
            up_reader, up_writer = await asyncio.open_connection(*self.target)
        except OSError:
            writer.close()
            return
        pair = [writer, up_writer]
        self._writers += pair
        await asyncio.gather(self._pump(_Pipe(reader, up_writer, True)),
                             self._pump(_Pipe(up_reader, writer, False)),
                             return_exceptions=True)
        for w in pair:
            w.close()
            with contextlib.suppress(ValueError):  # cut() may have cleared the list
                self._writers.remove(w)

    async def _pump(self, pipe: _Pipe) -> None:
        """Copy one direction; in ``stall`` or ``partition`` read nothing more (so the
        sender's buffers fill, as behind a peer that stopped reading), and in
        ``partition`` also hold back what was already read."""
        while True:
            while self.mode in ("stall", "partition"):
                await asyncio.sleep(0.01)
            try:
                data = await pipe.reader.read(CHUNK)
            except OSError:  # a reset (a killed peer): pass it on as a close, which also
                data = b""  # ends the other direction's read
            if not data:
                if not pipe.upstream and self.hold_closes:
                    self._held += 1
                    while self.hold_closes:
                        await asyncio.sleep(0.01)
                    self._held -= 1
                pipe.writer.close()
                return
            while self.mode == "partition":
                await asyncio.sleep(0.01)
            at = self.flip_in
            if pipe.upstream and at is not None:
                if at < len(data):
                    changed = bytearray(data)
                    changed[at] ^= 1
                    data, self.flip_in = bytes(changed), None
                else:
                    self.flip_in = at - len(data)
            pipe.writer.write(data)
            await pipe.writer.drain()
            pipe.moved += len(data)
            self.bytes_forwarded += len(data)
            if self.rate_bytes_per_s:
                await asyncio.sleep(len(data) / self.rate_bytes_per_s)
