"""The table data link: the garbler's table stream to the evaluator beside their
mutual-TLS connection rather than inside it (``--table-link``, the same on both servers).

Python's TLS record layer costs each server about half its CPU per run (16 KiB records,
copies through ``ssl``); garbled tables give nothing to anyone without the input labels,
which stay on TLS links, and every stream already ends with the garbler's signed digest,
which the evaluator checks before it answers (gc/attest.py). The modes:

- ``tls``: the stream runs on the TLS connection itself, as before.
- ``aead``: a second connection to the same port whose frames are sealed whole with
  AES-256-GCM under a key fresh per link (seal.py): confidential and authenticated frame
  by frame.
- ``digest``: a second connection with plain frames: no encryption, integrity from the
  signed digest; for servers on a private link.

Opening (``aead``, ``digest``): the garbler opens its TLS connection as ever; the
evaluator's ``capabilities`` to a garbler carry ``table_link``, a one-time ``link_token``
and, for ``aead``, the ``link_key``. The garbler connects again to the same address and
port (the evaluator tells the two kinds of connection apart by their first byte:
sharedport.py), writes PREAMBLE and the token, and waits for the evaluator's
``capabilities`` on the new link (sealed under the key: it proves both ends hold it).
Every session of the pair then runs on the data link as it would on TLS
(snail_garbler/streams.py); the TLS connection stays open beside it, and either ending
ends both. The peer of a data link is the garbler its TLS connection verified.

A connection to the port that is not TLS and brings anything but the preamble with a
token handed out in the last ``--handshake-timeout`` seconds and not used yet is dropped at
once and logged (``data_link_refused``): a stranger, a replay, a garbler too slow to use
its token. A stranger is dropped on the first byte that leaves the preamble, not held
for the timeout waiting for the rest of an opening that cannot be one.
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import secrets
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from . import messages
from .conn import Connection, format_addr
from .errors import TABLE_LINK, UNEXPECTED, ConnectionClosed, ProtocolError, RemoteError
from .frames import MAX_FRAME, BodyPool
from .logs import event
from .seal import EVALUATOR_TO_GARBLER, GARBLER_TO_EVALUATOR, KEY_BYTES, FrameSeal

MODES = messages.TABLE_LINKS
TLS, AEAD, DIGEST = MODES
DEFAULT_MODE = AEAD
TOKEN_BYTES = 32
PREAMBLE = b"snail-tables-1\n\x00"  # what the data port expects first, then the token
_OPENING = len(PREAMBLE) + TOKEN_BYTES


@dataclass
class Grant:
    """A token handed out to a garbler over its TLS connection ``control``."""

    control: Connection
    key: bytes | None
    until: float  # monotonic deadline for its use


class DataPort:
    """The evaluator's data port: hands out tokens, admits the links that bring one.

    ``opened(conn)`` is told of each admitted link (the daemon serves it as it serves the
    garbler's TLS connections)."""

    def __init__(self, mode: str, timeout: float, log: logging.Logger,
                 opened: Callable[[Connection], None], refused: Callable[[], None],
                 frame_timeout: float, pool: BodyPool) -> None:
        self.mode = mode
        self.timeout = timeout
        self.log = log
        self._opened, self._refused = opened, refused
        self._frame_timeout, self._pool = frame_timeout, pool
        self._grants: dict[bytes, Grant] = {}

    def grant(self, control: Connection) -> dict[str, Any]:
        """The fields a garbler's ``capabilities`` carry in this mode."""
        if self.mode == TLS:
            return {"table_link": TLS}
        self._expire()
        token = secrets.token_bytes(TOKEN_BYTES)
        key = secrets.token_bytes(KEY_BYTES) if self.mode == AEAD else None
        self._grants[token] = Grant(control, key, time.monotonic() + self.timeout)
        fields = {"table_link": self.mode, "link_token": token}
        return fields | ({"link_key": key} if key is not None else {})

    def gate(self) -> asyncio.BufferedProtocol:
        """The protocol of a connection that opened with something other than TLS: it
        must bring a token (sharedport.py)."""
        return _Gate(self)

    def admit(self, transport: asyncio.Transport, opening: bytes) -> None:
        """A connection's first bytes: hand it over to a served link if they bring a
        live token, else drop it."""
        where = _peer(transport)
        grant = self._take(opening)
        if grant is None:
            self.refuse(transport, "no valid token (unknown, used, or expired)")
            return
        if grant.control.ended:
            self.refuse(transport, "its TLS connection has closed")
            return
        seal = FrameSeal(grant.key, EVALUATOR_TO_GARBLER, GARBLER_TO_EVALUATOR) \
            if grant.key is not None else None
        conn = Connection(MAX_FRAME, frame_timeout=self._frame_timeout, pool=self._pool,
                          seal=seal, bound=grant.control.identity)
        transport.set_protocol(conn)
        conn.connection_made(transport)
        conn.tie(grant.control)
        event(self.log, "data_link_open", peer=conn.peer_name, address=where,
              table_link=self.mode)
        self._opened(conn)

    def refuse(self, transport: asyncio.BaseTransport, reason: str) -> None:
        self._refused()
        event(self.log, "data_link_refused", logging.WARNING, address=_peer(transport),
              reason=reason)
        transport.abort()

    def _take(self, opening: bytes) -> Grant | None:
        """The grant of the token in ``opening`` (used up), if it is live."""
        self._expire()
        if not hmac.compare_digest(opening[: len(PREAMBLE)], PREAMBLE):
            return None
        return self._grants.pop(opening[len(PREAMBLE):], None)

    def _expire(self) -> None:
        now = time.monotonic()
        for token in [t for t, g in self._grants.items() if g.until < now]:
            del self._grants[token]


class _Gate(asyncio.BufferedProtocol):
    """A data port connection until its opening is read (exactly that many bytes: the
    frames after it go to the link's own Connection), or the time for it is up."""

    def __init__(self, port: DataPort) -> None:
        self._port = port
        self._buf = bytearray(_OPENING)
        self._got = 0
        self._transport: asyncio.Transport | None = None
        self._timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = transport  # type: ignore[assignment]
        self._timer = asyncio.get_running_loop().call_later(
            self._port.timeout, self._late)

    def get_buffer(self, sizehint: int) -> memoryview:
        return memoryview(self._buf)[self._got :]

    def buffer_updated(self, nbytes: int) -> None:
        self._got += nbytes
        head = min(self._got, len(PREAMBLE))
        if self._buf[:head] != PREAMBLE[:head]:  # public bytes: no need for compare_digest
            self._end("its first bytes are not the data link's preamble")
        elif self._got == _OPENING and self._transport is not None:
            self._timer.cancel()
            transport, self._transport = self._transport, None
            self._port.admit(transport, bytes(self._buf))

    def eof_received(self) -> bool:
        self._end("it closed before its token")
        return False

    def connection_lost(self, exc: Exception | None) -> None:
        if self._timer is not None:
            self._timer.cancel()

    def _late(self) -> None:
        self._end(f"no token within {self._port.timeout:g} s")

    def _end(self, reason: str) -> None:
        if self._transport is not None:
            transport, self._transport = self._transport, None
            self._port.refuse(transport, reason)


async def dial(control: Connection, host: str, port: int, mode: str,
               timeout: float) -> Connection:
    """The connection a garbler streams tables on to the evaluator it reached over
    ``control`` (just opened, at ``host:port``): ``control`` itself in mode ``tls``, else
    a data link to the same port (module doc). ProtocolError (``table_link``) if the
    evaluator serves another mode: the operators' settings differ, no retry helps;
    ConnectionClosed naming the evaluator and the mode if the link cannot be opened.
    ``control`` is closed on either."""
    theirs = control.info.get("table_link", TLS)
    where = f"the evaluator at {format_addr(host, port)}"
    if theirs != mode:
        control.abort()
        raise ProtocolError(TABLE_LINK, f"{where} serves its table link as {theirs}, this "
                                        f"garbler as {mode}: --table-link must be the same "
                                        f"on both servers")
    if mode == TLS:
        return control
    key = control.info.get("link_key")
    seal = FrameSeal(key, GARBLER_TO_EVALUATOR, EVALUATOR_TO_GARBLER) if mode == AEAD \
        else None
    loop = asyncio.get_running_loop()
    conn: Connection | None = None
    try:
        if mode == AEAD and key is None:
            raise ProtocolError(UNEXPECTED, "its capabilities carry no link key")
        _, conn = await asyncio.wait_for(loop.create_connection(
            lambda: Connection(MAX_FRAME, seal=seal, bound=control.identity), host, port),
            timeout)
        conn.transport.write(PREAMBLE + control.info["link_token"])
        conn.info = await conn.expect("capabilities", timeout)
    except asyncio.CancelledError:
        control.abort()
        if conn is not None:
            conn.abort()
        raise
    except (OSError, asyncio.TimeoutError, TimeoutError, ConnectionClosed, ProtocolError,
            RemoteError, KeyError) as exc:
        control.abort()
        if conn is not None:
            conn.abort()
        raise ConnectionClosed(f"the table link ({mode}) to {where} could not be opened: "
                               f"{exc}") from None
    conn.tie(control)
    return conn


def _peer(transport: asyncio.BaseTransport) -> str:
    peer = transport.get_extra_info("peername")
    return format_addr(*peer[:2]) if peer else "?"
