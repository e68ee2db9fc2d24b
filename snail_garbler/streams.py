"""The garbler's connections to the evaluator: one session's table stream at a time,
pooled between sessions, and kept in step however a session ends.

A connection carries ``session_start``, that session's ``tables`` frames and then the
evaluator's verdict for it (``done`` or ``error`` {sid}); only then may it carry the next
session. A session may end early on either side without costing the connection:

- the garbler ends it (its client cancelled or left, its reservation was evicted, the
  daemon stops) while frames remain: it sends ``error`` {sid} in place of the next frame
  and reads the evaluator's one verdict for that sid;
- the evaluator ends it (its client cancelled, a timeout, an eviction, a refused sid): it
  sends ``error`` {sid} and discards that session's frames until the garbler's own
  ``error`` {sid}, which the garbler sends on reading the evaluator's, unless its own
  was already on the way (both ended it at once: each side's error answers the other's).

A verdict still due when the session's work is done (a reservation's tables wait at the
evaluator for its client's labels) is awaited in the background: the session's slot is
free at once, and the connection returns to the pool when the verdict comes. Only a
connection broken or out of step (an unexpected message, a timeout) is closed.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

from snail_common.net import messages
from snail_common.net.conn import Connection, connect
from snail_common.net.datalink import TLS, dial
from snail_common.net.errors import UNEXPECTED, ConnectionClosed, ProtocolError, RemoteError
from snail_common.net.logs import event
from snail_common.net.replicas import Address, Replicas

MAX_IDLE = 8  # pooled idle connections per evaluator replica
POOL_IDLE_S = 5.0  # a pooled connection unused this long is closed (clients have left)


class State(enum.Enum):
    IDLE = "idle"  # nothing of a session on it
    STREAMING = "streaming"  # session_start sent, frames remain
    SENT = "sent"  # every frame sent: the verdict is due
    BROKEN = "broken"


@dataclass(eq=False)
class TableLink:
    """A connection to one evaluator replica and where its current session stands."""

    where: Address
    conn: Connection
    state: State = State.IDLE

    def start(self, msg: dict) -> int:
        """Send a session's ``session_start``; the bytes written."""
        self.state = State.STREAMING
        return self.conn.write(msg)

    async def verdict(self, sid: bytes, timeout: float, ended_here: bool = False) -> None:
        """The evaluator's verdict on ``sid`` within ``timeout``: ``done`` returns;
        ``error`` raises RemoteError once the connection is in step again (the garbler's
        own ``error`` answers it, unless ``ended_here``: the garbler's was sent first);
        an ``error`` of no session ends the link with the evaluator's word (RemoteError:
        its code, ``link`` or ``digest`` for tables that reached it changed, goes on to the
        client). Anything else breaks the link (ProtocolError or ConnectionClosed)."""
        try:
            msg, _ = await self.conn.recv(timeout)
        except BaseException:
            self.state = State.BROKEN
            raise
        if msg["t"] == "done" and msg["sid"] == sid and self.state is State.SENT:
            self.state = State.IDLE
            return
        if msg["t"] == "error" and msg.get("sid") == sid:
            if not ended_here:
                self.conn.post(messages.error(msg["code"], "the garbler ends the stream", sid))
            self.state = State.IDLE
            raise RemoteError(msg["code"], msg["message"], sid)
        self.state = State.BROKEN
        if msg["t"] == "error" and msg.get("sid") is None:  # it closes the link next
            raise RemoteError(msg["code"], msg["message"])
        if msg["t"] == "bye":
            raise ConnectionClosed("the evaluator is shutting down")
        raise ProtocolError(UNEXPECTED, f"the evaluator sent {msg['t']} mid-session")


class TableLinks:
    """The pool of connections to the evaluator replicas this garbler may dial."""

    def __init__(self, evaluators: Replicas, ctx, handshake_timeout: float,
                 verdict_timeout: float, log: logging.Logger,
                 closed: Callable[[], None] = lambda: None, table_link: str = TLS) -> None:
        self.evaluators = evaluators
        self.ctx = ctx
        self.table_link = table_link  # the tables' own connection beside TLS, or TLS
        self.handshake_timeout = handshake_timeout
        self.verdict_timeout = verdict_timeout  # a held reservation's verdict comes late
        self.log = log
        self.closed = closed  # told when a link closes (the daemon sweeps its memory)
        self.idle: dict[Address, list[Connection]] = {}
        self._pooled: dict[Connection, float] = {}  # when each idle one was pooled
        self._settling: set[asyncio.Task] = set()
        self.closing = False

    @property
    def settling(self) -> int:
        """Streams sent whose verdict is still due."""
        return len(self._settling)

    async def acquire(self, named: str | None, instance: str | None) -> TableLink:
        """A connection to the evaluator replica a request names (forbidden outside this
        garbler's --evaluator names: snail_common.net.replicas)."""
        where, conn = await self.evaluators.locate(named, instance, "evaluator", self._take,
                                                   self._pool)
        return TableLink(where, conn)

    def end(self, link: TableLink, sid: bytes, code: str, reason: str) -> None:
        """The session on ``link`` is over for the garbler (module doc): pooled if the link
        is in step; if frames remain, ``error`` {sid} (``code``, ``reason``) ends the
        stream; a verdict still due is awaited in the background."""
        if link.conn.ended:
            link.state = State.BROKEN
        if link.state is State.STREAMING:
            try:
                link.conn.write(messages.error(code, reason, sid))
            except ConnectionClosed:
                link.state = State.BROKEN
        if link.state is State.IDLE:
            self._pool(link.where, link.conn)
        elif link.state is State.BROKEN:
            link.conn.abort()
        else:
            task = asyncio.get_running_loop().create_task(
                self._settle(link, sid, ended_here=link.state is State.STREAMING))
            self._settling.add(task)
            task.add_done_callback(self._settling.discard)

    async def _settle(self, link: TableLink, sid: bytes, ended_here: bool) -> None:
        """Wait for the verdict on ``sid``, then pool the link; close it if none comes."""
        link.state = State.SENT if not ended_here else link.state
        try:
            await link.verdict(sid, self.verdict_timeout, ended_here)
        except RemoteError as exc:
            if link.state is State.BROKEN:  # the evaluator ended the link itself
                link.conn.abort()
                event(self.log, "stream_link_closed", logging.INFO, sid=sid,
                      reason=f"the evaluator ended the link: {exc}")
                return
            # else in step: the evaluator ended the session (its client was told)
        except (ProtocolError, ConnectionClosed, TimeoutError, asyncio.CancelledError) as exc:
            link.conn.abort()
            if not isinstance(exc, asyncio.CancelledError):
                event(self.log, "stream_link_closed", logging.INFO, sid=sid,
                      reason=f"no verdict for a session it streamed: {exc}")
            return
        self._pool(link.where, link.conn)

    async def _take(self, addr: Address) -> Connection:
        """A pooled idle connection to the replica at ``addr``, else a new one."""
        pool = self.idle.get(addr, [])
        while pool:
            conn = pool.pop()
            self._pooled.pop(conn, None)
            if conn.idle:
                return conn
            await conn.close()  # something arrived while idle (a bye): not reusable
        control = await connect(*addr, self.ctx, "garbler", "evaluator",
                                self.handshake_timeout,
                                server_name=self.evaluators.server_name(addr))
        return await dial(control, *addr, self.table_link, self.handshake_timeout)

    def _pool(self, addr: Address, conn: Connection) -> None:
        pool = self.idle.setdefault(addr, [])
        if conn.idle and len(pool) < MAX_IDLE and not self.closing:
            pool.append(conn)
            self._pooled[conn] = time.monotonic()
            asyncio.get_running_loop().call_later(POOL_IDLE_S, self._expire, addr, conn)
        else:
            conn.abort()

    def _expire(self, addr: Address, conn: Connection) -> None:
        """Close ``conn`` if it is still in the pool, unused since it was put there (one
        taken and given back meanwhile has a later timer of its own)."""
        pool = self.idle.get(addr, [])
        since = self._pooled.get(conn)
        if conn in pool and since is not None \
                and time.monotonic() - since >= POOL_IDLE_S * 0.99:
            pool.remove(conn)
            del self._pooled[conn]
            conn.abort()
            self.closed()

    async def close(self) -> None:
        """Shutdown: verdicts still due are no longer awaited; pooled links say bye."""
        self.closing = True
        for task in list(self._settling):
            task.cancel()
        await asyncio.gather(*self._settling, return_exceptions=True)
        idle = [conn for pool in self.idle.values() for conn in pool]
        self.idle.clear()
        self._pooled.clear()
        with contextlib.suppress(Exception):
            await asyncio.gather(*(c.close(messages.make("bye")) for c in idle),
                                 return_exceptions=True)
