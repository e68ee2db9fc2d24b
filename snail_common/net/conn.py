"""One framed, mutually authenticated TLS connection, as used by all three roles.

TLS decrypts straight into the frame buffers (a BufferedProtocol, see
frames.FrameReader); decoded frames wait in a small inbox, so the next frames are read
and decrypted while the consumer works on the current one (the evaluator evaluates frame
k while frame k+1 arrives), and reading pauses once the inbox is full: memory per
connection stays bounded and back-pressure reaches the sender through TCP. ``drain``
waits above a write high-water mark, which is what throttles a garbler faster than its
evaluator.

Opening: the connecting side sends ``hello``, the server answers ``capabilities`` (or an
``error`` and closes). The authoritative role of a peer is the one in its certificate.

Links with a client or a map owner at one end are dialled for small bursts (dial.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import socket
import ssl
import sys
from collections.abc import Callable
from typing import Any

from . import messages
from .dial import BURST_ROLES, dial_tcp
from .errors import (
    FORBIDDEN,
    TIMEOUT,
    UNEXPECTED,
    ConnectionClosed,
    ProtocolError,
    RemoteError,
)
from .frames import MAX_FRAME, BodyPool, FrameReader, encode
from .seal import FrameSeal
from .tls import Identity, peer_identity

SOFTWARE = "snail/0.1"
WRITE_HIGH = 4 << 20  # drain() waits while more than this is buffered for sending
INBOX = 3  # decoded frames read ahead
_ADDR = re.compile(r"^(?:\[(?P<v6>[0-9a-fA-F:.]+)\]|(?P<host>[A-Za-z0-9_.-]+)):(?P<port>\d{1,5})$")


def parse_addr(text: str) -> tuple[str, int]:
    """``HOST:PORT`` or ``[IPv6]:PORT`` -> (host, port); ValueError naming the problem."""
    m = _ADDR.match(text.strip())
    if not m or int(m["port"]) > 65535:
        raise ValueError(f"address {text!r} is not HOST:PORT")
    return m["v6"] or m["host"], int(m["port"])


def format_addr(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


class Connection(asyncio.BufferedProtocol):
    """Framed messages over a TLS transport with a verified peer role.

    The transport decrypts into a FrameReader's buffers; decoded messages wait in a small
    inbox, and reading pauses while it is full. Writes go straight to the transport;
    ``drain`` waits while its buffer is above WRITE_HIGH.
    """

    def __init__(self, max_frame: int = MAX_FRAME, inbox: int = INBOX,
                 on_open: Callable[[Connection], None] | None = None,
                 frame_timeout: float | None = None, pool: BodyPool | None = None,
                 seal: FrameSeal | None = None, bound: Identity | None = None) -> None:
        # a table data link (datalink.py) has no certificate of its own: its peer is the
        # one its control connection verified (``bound``), its frames sealed or plain
        self._bound = bound
        self._seal = seal
        self._tied: set[Connection] = set()  # connections that end with this one
        self.peer_role = bound.role if bound is not None else ""  # from the certificate
        self.identity: Identity | None = bound
        self.frame_timeout = frame_timeout  # a begun frame must be complete within this
        self._frame_timer: asyncio.TimerHandle | None = None
        self.peer: Any = None
        self.info: dict[str, Any] = {}  # the peer's hello or capabilities
        self.bytes_in = 0
        self.bytes_out = 0
        self._frames = FrameReader(max_frame, pool, seal)
        self._inbox: asyncio.Queue = asyncio.Queue()
        self._inbox_size = inbox
        self._reading_paused = False
        self._ended = False
        self._write_paused = False
        self._drain_waiters: list[asyncio.Future] = []
        self._lost: Exception | None = None
        self._on_open = on_open
        self.transport: asyncio.Transport | None = None

    @property
    def peer_name(self) -> str:
        """The peer's certificate name (a client's own name, else its role)."""
        return self.identity.name if self.identity is not None else ""

    # ---- asyncio protocol callbacks --------------------------------------------------------
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]
        self.peer = transport.get_extra_info("peername")
        transport.set_write_buffer_limits(high=WRITE_HIGH)  # type: ignore[attr-defined]
        if self._bound is not None:
            return  # a data link handed over by its gate: the peer is known
        try:
            self.identity = peer_identity(transport.get_extra_info("ssl_object"))
            self.peer_role = self.identity.role
        except ValueError:
            self.peer_role = ""  # accept() refuses it
        if self._on_open is not None:
            self._on_open(self)

    def get_buffer(self, sizehint: int) -> memoryview:
        return self._frames.buffer()

    def buffer_updated(self, nbytes: int) -> None:
        try:
            done = self._frames.filled(nbytes)
            for item in done:
                self.bytes_in += item[1]
                self._inbox.put_nowait(item)
            self._watch_frame(bool(done))
        except ProtocolError as exc:
            self._end(exc.with_traceback(None))  # kept in the inbox: nothing else with it
            self._frames.release()  # a refused frame's bytes are not kept either
            if not self._reading_paused and self.transport is not None:
                self._reading_paused = True
                self.transport.pause_reading()
            return
        if self._inbox.qsize() >= self._inbox_size and not self._reading_paused:
            self._reading_paused = True
            self.transport.pause_reading()

    def _watch_frame(self, completed: bool) -> None:
        """Time a begun frame from its first bytes: a peer that announces a frame and
        then trickles it (or stops) loses the connection after ``frame_timeout``."""
        if self.frame_timeout is None:
            return
        if self._frame_timer is not None and (completed or not self._frames.partial):
            self._frame_timer.cancel()
            self._frame_timer = None
        if self._frame_timer is None and self._frames.partial:
            self._frame_timer = asyncio.get_running_loop().call_later(
                self.frame_timeout, self._frame_late)

    def _frame_late(self) -> None:
        self._frame_timer = None
        self._end(ProtocolError(TIMEOUT, f"a frame begun {self.frame_timeout:g} s ago is "
                                         f"still incomplete"))
        self._frames.release()
        if self.transport is not None:
            self.transport.abort()

    def eof_received(self) -> bool:
        self._end(ConnectionClosed(f"the {self.peer_role or 'peer'} closed the connection"
                                   + (" mid-frame" if self._frames.partial else "")))
        return False

    def connection_lost(self, exc: Exception | None) -> None:
        if self._frame_timer is not None:
            self._frame_timer.cancel()
            self._frame_timer = None
        reason = f": {exc}" if exc else ""
        self._lost = ConnectionClosed(f"the connection to the {self.peer_role or 'peer'} "
                                      f"was lost{reason}")
        self._end(self._lost)
        for waiter in self._drain_waiters:
            if not waiter.done():
                waiter.set_exception(self._lost)
        self._drain_waiters.clear()
        self._cut_tied()

    def pause_writing(self) -> None:
        self._write_paused = True

    def resume_writing(self) -> None:
        self._write_paused = False
        for waiter in self._drain_waiters:
            if not waiter.done():
                waiter.set_result(None)
        self._drain_waiters.clear()

    # ---- interface -------------------------------------------------------------------------
    @property
    def ended(self) -> bool:
        """True once nothing more can be received (EOF, error, closed)."""
        return self._ended

    @property
    def idle(self) -> bool:
        """Open with nothing unread: safe to reuse for a new session."""
        return not self._ended and self._inbox.empty()

    @property
    def socket(self) -> socket.socket | None:
        """The transport's socket (None before it is made and once it has gone)."""
        return self.transport.get_extra_info("socket") if self.transport else None

    def peer_closed(self) -> bool:
        """Whether the peer's end is closed, read off the socket now: a loop that was not
        running (a blocking runner between calls) has not yet taken in the FIN or reset,
        so ``ended`` is still False. Data queued ahead of a FIN hides it."""
        if self._ended:
            return True
        sock = self.socket
        if sock is None:
            return False
        try:  # a duplicate descriptor: the loop's transport socket allows no recv
            with socket.socket(fileno=socket.dup(sock.fileno())) as probe:
                return probe.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
        except BlockingIOError:
            return False
        except OSError:  # reset, or the descriptor is already gone
            return True

    def _end(self, reason: Exception) -> None:
        """No more input: queue ``reason`` for the consumer (once)."""
        if not self._ended:
            self._ended = True
            self._inbox.put_nowait((reason, 0))

    async def recv(self, timeout: float | None = None) -> tuple[dict[str, Any], int]:
        """The next message and its wire size. Raises ConnectionClosed at the end,
        ProtocolError for a bad frame from the peer, TimeoutError after ``timeout``."""
        try:
            item = await asyncio.wait_for(self._inbox.get(), timeout)
        except asyncio.TimeoutError:
            raise TimeoutError(f"no message from the {self.peer_role} for {timeout:g} s") \
                from None
        if self._reading_paused and self._inbox.qsize() < self._inbox_size and not self._ended:
            self._reading_paused = False
            self.transport.resume_reading()
        if isinstance(item[0], Exception):
            self._inbox.put_nowait(item)  # every later recv raises the same
            raise item[0]
        return item

    async def expect(self, kind: str, timeout: float | None = None) -> dict[str, Any]:
        """The next message, which must be of type ``kind`` (an ``error`` raises
        RemoteError, anything else ProtocolError)."""
        msg, _ = await self.recv(timeout)
        if msg["t"] == "error":
            raise RemoteError(msg["code"], msg["message"], msg.get("sid"))
        if msg["t"] != kind:
            raise ProtocolError(UNEXPECTED, f"expected {kind}, the {self.peer_role} sent "
                                            f"{msg['t']}")
        return msg

    def write(self, msg: dict[str, Any]) -> int:
        """Queue one frame without waiting (frames are never interleaved); its size. The
        frame's buffers go to the transport in one call: TLS encrypts them and hands the
        socket one write, not one per buffer (length, header, table data)."""
        if self._lost is not None or self.transport is None or self.transport.is_closing():
            raise ConnectionClosed(f"the connection to the {self.peer_role} is closed")
        parts = encode(msg) if self._seal is None else self._seal.seal(
            encode(msg), written=not self.transport.get_write_buffer_size())
        self.transport.writelines(parts)
        size = sum(len(p) for p in parts)
        self.bytes_out += size
        return size

    def recycle(self, data: memoryview) -> None:
        """Hand back the data of a received ``tables`` frame once nothing reads it any
        more: the next frame is received into its buffer (frames.FrameReader)."""
        self._frames.recycle(data)

    def post(self, msg: dict[str, Any]) -> None:
        """Write a notice if the connection is still open (errors to a peer that may
        already be gone)."""
        with contextlib.suppress(ConnectionClosed):
            self.write(msg)

    async def drain(self) -> None:
        """Wait while the send buffer is above its high-water mark."""
        if self._lost is not None:
            raise self._lost
        if self._write_paused:
            waiter = asyncio.get_running_loop().create_future()
            self._drain_waiters.append(waiter)
            await waiter

    async def send(self, msg: dict[str, Any]) -> int:
        """Write one frame, then drain."""
        size = self.write(msg)
        await self.drain()
        return size

    async def close(self, last: dict[str, Any] | None = None, timeout: float = 2.0) -> None:
        """Send ``last`` (e.g. an error or bye) if possible, then close the stream."""
        if last is not None:
            self.post(last)
        self._end(ConnectionClosed(f"the connection to the {self.peer_role} was closed"))
        if self.transport is None or self._lost is not None:
            return
        self.transport.close()
        deadline = asyncio.get_running_loop().time() + timeout
        while self._lost is None and asyncio.get_running_loop().time() < deadline:
            await asyncio.sleep(0.01)
        if self._lost is None:
            self.transport.abort()

    def abort(self) -> None:
        """Drop the connection at once (a stream cut mid-session cannot be resynced)."""
        self._end(ConnectionClosed(f"the connection to the {self.peer_role} was aborted"))
        if self.transport is not None:
            self.transport.abort()
        self._cut_tied()

    def tie(self, other: Connection) -> None:
        """End ``other`` with this one and this one with ``other`` (a table data link
        and its control connection: neither is any use alone)."""
        self._tied.add(other)
        other._tied.add(self)

    @property
    def data_link(self) -> bool:
        """Whether this is a table data link (its peer verified by another connection)."""
        return self._bound is not None

    @property
    def tied_open(self) -> bool:
        """Whether a connection tied to this one is still open (a control connection is
        busy while its data link is)."""
        return any(not other.ended for other in self._tied)

    def _cut_tied(self) -> None:
        tied, self._tied = self._tied, set()
        for other in tied:
            other._tied.discard(self)
            other.abort()


async def connect(host: str, port: int, ctx: ssl.SSLContext, role: str, expect_role: str,
                  timeout: float = 10.0, max_frame: int = MAX_FRAME,
                  server_name: str | None = None, sock: socket.socket | None = None,
                  factory: Callable[[], Connection] | None = None) -> Connection:
    """Open a TLS connection as ``role`` to a server that must be ``expect_role``;
    returns it after the hello/capabilities exchange. The server's certificate must name
    ``server_name`` (default ``host``): a replica dialled at the address a service name
    resolved to is checked against the service name, which its certificate carries.
    ``sock``: a socket already connected to that server some other way (a relay's end:
    snail_client/relay.py), over which TLS runs instead of dialling ``host``;
    ``factory``: the connection object (a Connection of ``max_frame`` by default)."""
    where = f"the {expect_role} at {format_addr(host, port)}"
    try:
        _, conn = await asyncio.wait_for(_open(
            factory or (lambda: Connection(max_frame)), host, port, ctx, timeout,
            bursts=role in BURST_ROLES or expect_role in BURST_ROLES,
            server_name=server_name or host, sock=sock), timeout)
    except asyncio.TimeoutError:
        raise ConnectionClosed(f"connecting to {where} timed out") from None
    except (OSError, ssl.SSLError) as exc:
        raise ConnectionClosed(f"cannot connect to {where}: {exc}") from None
    if conn.peer_role != expect_role:
        conn.abort()
        got = f"the {conn.peer_role}'s" if conn.peer_role else "no snail"
        raise ConnectionClosed(f"{format_addr(host, port)} presents {got} certificate, "
                               f"expected the {expect_role}'s")
    try:
        conn.write(messages.make("hello", role=role, software=SOFTWARE, max_frame=max_frame))
        conn.info = await conn.expect("capabilities", timeout)
    except (TimeoutError, ConnectionClosed, ProtocolError, RemoteError) as exc:
        conn.abort()
        raise ConnectionClosed(f"opening a session with {where} failed: {exc}") from None
    except BaseException:  # cancelled mid-opening (its session was): the socket goes too
        conn.abort()
        raise
    return conn


async def _open(factory: Callable[[], Connection], host: str, port: int,
                ctx: ssl.SSLContext, timeout: float, bursts: bool,
                server_name: str, sock: socket.socket | None = None
                ) -> tuple[Any, Connection]:
    """create_connection, on a socket set up for small bursts before it connects when
    ``bursts`` (dial.py), or over ``sock``, connected already."""
    loop = asyncio.get_running_loop()
    if sock is None and bursts:
        sock = await dial_tcp(host, port)
    if sock is not None:
        return await loop.create_connection(factory, sock=sock, ssl=ctx,
                                            server_hostname=server_name,
                                            ssl_handshake_timeout=timeout)
    return await loop.create_connection(factory, host, port, ssl=ctx,
                                        server_hostname=server_name,
                                        ssl_handshake_timeout=timeout)


async def accept(conn: Connection, capabilities: dict[str, Any], allowed: tuple[str, ...],
                 timeout: float = 10.0,
                 refusal: Callable[[Connection], ProtocolError | None] | None = None) -> None:
    """Server side of the opening: check the certificate's role is ``allowed``, read the
    peer's hello, ask ``refusal`` (revoked, over a quota ...), answer ``capabilities``. On
    failure the peer gets an ``error``, the stream is closed and ProtocolError (or
    ConnectionClosed, TimeoutError) is raised. Refusals come after the hello is read: a
    peer still writing its hello to a closed socket could lose the error to a reset."""
    try:
        if not conn.peer_role:
            raise ProtocolError(FORBIDDEN, "the peer certificate names no snail role")
        if conn.peer_role not in allowed:
            raise ProtocolError(FORBIDDEN, f"a {conn.peer_role} may not connect to the "
                                           f"{capabilities['role']}")
        hello = await conn.expect("hello", timeout)
        if hello["role"] != conn.peer_role:
            raise ProtocolError(FORBIDDEN, f"hello claims role {hello['role']!r} but the "
                                           f"certificate is a {conn.peer_role}'s")
        refused = refusal(conn) if refusal is not None else None
        if refused is not None:
            raise refused
    except ProtocolError as exc:
        await conn.close(messages.error(exc.code, exc.message))
        raise
    except BaseException:
        await conn.close()
        raise
    conn.info = hello
    conn.write(capabilities)


def new_event_loop() -> asyncio.AbstractEventLoop:
    """A fresh uvloop event loop (asyncio's own on Windows, where uvloop does not exist)."""
    if sys.platform == "win32":
        return asyncio.new_event_loop()
    import uvloop

    return uvloop.new_event_loop()
