"""One listening port for the evaluator's TLS connections and the garbler's table data
links (datalink.py): a connection's first byte says which.

Every TLS connection opens with a handshake record (byte 0x16); a data link opens with
datalink.PREAMBLE, which starts with another byte. The byte is peeked, not read, so a TLS
connection reaches its handshake whole. One port means nothing changes where ports are
named (compose, the swarm stack, Kubernetes, the network lab's shaped links, a firewall):
the data link goes wherever the TLS connection went.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import ssl
from collections.abc import Callable

from .conn import format_addr
from .dial import prefer_bursts

TLS_HANDSHAKE = 0x16  # the content type of a TLS handshake record
BACKLOG = 128


class SharedPort:
    """Accepts on ``host:port``; a TLS connection gets ``tls_protocol()`` over ``ctx``,
    any other gets ``other_protocol()`` on the plain socket. A connection that sends
    nothing within ``timeout`` is closed and told to ``silent(address)``."""

    def __init__(self, tls_protocol: Callable[[], asyncio.BaseProtocol], ctx: ssl.SSLContext,
                 other_protocol: Callable[[], asyncio.BaseProtocol], timeout: float,
                 silent: Callable[[str], None]) -> None:
        self._tls, self._ctx, self._other = tls_protocol, ctx, other_protocol
        self._timeout, self._silent = timeout, silent
        self.sockets: list[socket.socket] = []
        self._waiting: dict[socket.socket, asyncio.TimerHandle] = {}
        self._tasks: set[asyncio.Task] = set()

    async def start(self, host: str, port: int) -> SharedPort:
        """Listen on every address ``host`` resolves to (``port`` 0: a free one, the same
        for all)."""
        loop = asyncio.get_running_loop()
        for family, kind, proto, _, addr in await loop.getaddrinfo(
                host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE):
            sock = socket.socket(family, kind, proto)
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                if family == socket.AF_INET6:
                    sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
                prefer_bursts(sock)  # accepted links inherit it (dial.py module doc)
                sock.bind(addr[:2] if not self.sockets else (addr[0], self.port))
                sock.listen(BACKLOG)
                sock.setblocking(False)
            except OSError:
                sock.close()
                self.close()
                raise
            self.sockets.append(sock)
            loop.add_reader(sock.fileno(), self._accept, sock)
        return self

    @property
    def port(self) -> int:
        return self.sockets[0].getsockname()[1]

    def close(self) -> None:
        """Stop accepting (connections already handed over go on)."""
        loop = asyncio.get_running_loop()
        for sock in self.sockets:
            with contextlib.suppress(ValueError, OSError):
                loop.remove_reader(sock.fileno())
            sock.close()
        self.sockets = []
        for sock, timer in list(self._waiting.items()):
            self._drop(sock, timer)

    async def wait_closed(self) -> None:
        await asyncio.gather(*self._tasks, return_exceptions=True)

    def _accept(self, listening: socket.socket) -> None:
        loop = asyncio.get_running_loop()
        for _ in range(BACKLOG):
            try:
                sock, _ = listening.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # out of descriptors, a reset before accept: the next one
                return
            sock.setblocking(False)
            self._waiting[sock] = loop.call_later(self._timeout, self._late, sock)
            loop.add_reader(sock.fileno(), self._first_byte, sock)

    def _first_byte(self, sock: socket.socket) -> None:
        try:
            first = sock.recv(1, socket.MSG_PEEK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            first = b""
        timer = self._waiting.pop(sock, None)
        asyncio.get_running_loop().remove_reader(sock.fileno())
        if timer is not None:
            timer.cancel()
        if not first:  # closed (or reset) before a byte
            sock.close()
            return
        task = asyncio.get_running_loop().create_task(self._hand_over(sock, first[0]))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _hand_over(self, sock: socket.socket, first: int) -> None:
        loop = asyncio.get_running_loop()
        try:
            if first == TLS_HANDSHAKE:
                await loop.connect_accepted_socket(self._tls, sock, ssl=self._ctx,
                                                   ssl_handshake_timeout=self._timeout)
            else:
                await loop.connect_accepted_socket(self._other, sock)
        except (OSError, ssl.SSLError):
            sock.close()  # a failed handshake is reported by the context (listener.py)

    def _late(self, sock: socket.socket) -> None:
        timer = self._waiting.get(sock)
        if timer is not None:
            self._silent(_address(sock))
            self._drop(sock, timer)

    def _drop(self, sock: socket.socket, timer: asyncio.TimerHandle) -> None:
        timer.cancel()
        self._waiting.pop(sock, None)
        with contextlib.suppress(ValueError, OSError):
            asyncio.get_running_loop().remove_reader(sock.fileno())
        sock.close()


def _address(sock: socket.socket) -> str:
    try:
        return format_addr(*sock.getpeername()[:2])
    except OSError:
        return "?"
