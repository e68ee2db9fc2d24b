"""The client's server connections: frames dispatched to sessions by sid.

A client keeps one TLS connection to each server for its whole lifetime; every session
(invocation, prepared or running) has an ``Inbox`` on each link into which the link's
dispatcher drops that session's messages, or the link's failure.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from typing import Any

import numpy as np

from snail_common.net import messages
from snail_common.net.chunks import LabelAssembler
from snail_common.net.conn import Connection, format_addr
from snail_common.net.errors import UNEXPECTED, ConnectionClosed, ProtocolError, RemoteError


class ServiceError(Exception):
    """A secure invocation failed (network, server error, timeout or integrity);
    ``code`` is the server's error code when a server refused or failed the session,
    ``link`` the server connection that failed or said so, when one did, and ``retry``
    whether the invocation may be run again (on another replica: secure.py)."""

    def __init__(self, message: str, code: str | None = None,
                 link: Link | None = None, retry: bool | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.link = link
        self.retry = retry  # whether another replica may serve it (None: only if busy)


class Inbox:
    """The messages (or the failure) one server sent about one session, in order."""

    def __init__(self) -> None:
        self._items: deque[tuple[Any, int]] = deque()
        self._ready = asyncio.Event()

    def put(self, item: Any, size: int = 0) -> None:
        self._items.append((item, size))
        self._ready.set()

    async def get(self) -> tuple[Any, int]:
        while not self._items:
            self._ready.clear()
            await self._ready.wait()
        return self._items.popleft()

    async def answered(self) -> None:
        """Return once the server has said something of this session (without taking it:
        ``get`` still returns it)."""
        while not self._items:
            self._ready.clear()
            await self._ready.wait()

    @property
    def empty(self) -> bool:
        return not self._items

    @property
    def failed(self) -> bool:
        """The server already gave up this session (an error or a broken link)."""
        return any(isinstance(m, Exception) or m["t"] == "error" for m, _ in self._items)

    @property
    def error_code(self) -> str | None:
        """The code of the server's ``error`` for this session, if one came."""
        return next((m["code"] for m, _ in self._items
                     if not isinstance(m, Exception) and m["t"] == "error"), None)


DEFAULT_LINK_TIMEOUT = 30.0


class Link:
    """One server connection, its frames dispatched to waiting sessions by sid.

    A link some session waits on and that has been quiet for a fifth of ``link_timeout``
    is probed with a ``health_request``; one that stays silent for ``link_timeout`` is
    declared broken. Without this a partitioned or stalled link (TCP keeps both ends
    open, nothing arrives) would hold the client until its whole-run timeout."""

    def __init__(self, conn: Connection, link_timeout: float = DEFAULT_LINK_TIMEOUT) -> None:
        self.conn = conn
        self.role = conn.peer_role
        self.waiting: dict[bytes, Inbox] = {}
        self.health: asyncio.Future | None = None
        self.failure: Exception | None = None
        self.link_timeout = link_timeout
        self.last_heard = time.monotonic()
        loop = asyncio.get_running_loop()
        self._task = loop.create_task(self._dispatch())
        self._watch = loop.create_task(self._watchdog())

    @property
    def alive(self) -> bool:
        return self.failure is None and not self.conn.ended

    def reusable(self) -> bool:
        """Alive, also by the socket's own word (see Connection.peer_closed): a server
        that restarted while this client was idle is found here, before a run uses it."""
        return self.alive and not self.conn.peer_closed()

    @property
    def where(self) -> str:
        peer = self.conn.peer
        return f"the {self.role} at {format_addr(*peer[:2])}" if peer else f"the {self.role}"

    async def _dispatch(self) -> None:
        try:
            while True:
                msg, size = await self.conn.recv()
                self.last_heard = time.monotonic()
                sid = msg.get("sid")
                if sid is not None:
                    inbox = self.waiting.get(sid)
                    if inbox is not None:  # else: a session already given up
                        inbox.put(msg, size)
                elif msg["t"] == "health":  # asked for, or the watchdog's probe
                    if self.health and not self.health.done():
                        self.health.set_result(msg)
                elif msg["t"] == "error":
                    raise RemoteError(msg["code"], msg["message"])
                elif msg["t"] == "bye":
                    raise ConnectionClosed(f"the {self.role} is shutting down")
                else:
                    raise ProtocolError(UNEXPECTED, f"the {self.role} sent {msg['t']}")
        except (ConnectionClosed, ProtocolError, RemoteError) as exc:
            self._broken(exc)

    async def _watchdog(self) -> None:
        probe_after = self.link_timeout / 5
        probed = 0.0
        while self.alive:
            await asyncio.sleep(probe_after / 2)
            quiet = time.monotonic() - self.last_heard
            if not self.waiting:
                self.last_heard, probed = time.monotonic(), 0.0  # nothing owed: no clock
            elif quiet > self.link_timeout:
                self._broken(ConnectionClosed(
                    f"nothing from the {self.role} for {quiet:.0f} s while a session waited "
                    f"(--link-timeout {self.link_timeout:g}): the link is partitioned or "
                    f"the server stalled"))
            elif quiet > probe_after and probed < self.last_heard:
                probed = time.monotonic()
                self.conn.post(messages.make("health_request"))

    def _broken(self, exc: Exception) -> None:
        if self.failure is not None:
            return  # the first cause is the one to report
        self.failure = exc
        for inbox in self.waiting.values():
            inbox.put(exc)
        if self.health and not self.health.done():
            self.health.set_exception(exc)
        self.conn.abort()

    def open(self, sid: bytes) -> Inbox:
        inbox = Inbox()
        if self.failure is not None:
            inbox.put(self.failure)
        self.waiting[sid] = inbox
        return inbox

    def cancel(self, sid: bytes) -> None:
        """Tell the server to drop a session this client gave up (if the link lives)."""
        self.waiting.pop(sid, None)
        if self.alive:
            self.conn.post(messages.error("aborted", "the client gave up the session", sid))

    async def close(self) -> None:
        self._task.cancel()
        self._watch.cancel()
        await asyncio.gather(self._task, self._watch, return_exceptions=True)
        await self.conn.close(messages.make("bye"))


async def labels_and_stats(link: Link, inbox: Inbox, kind: str,
                           n_out: int) -> tuple[np.ndarray, int, dict[str, Any]]:
    """Read one server's label chunks, then its stats, for a session."""
    labels = LabelAssembler(kind, n_out)
    received = 0
    while True:
        msg, size = await inbox.get()
        if isinstance(msg, Exception):
            raise ServiceError(f"{link.where}: {msg}", link=link)
        received += size
        if msg["t"] == "error":
            raise ServiceError(f"{link.where} reported {msg['code']}: {msg['message']}",
                               msg["code"], link)
        if msg["t"] == kind:
            try:
                labels.add(msg)
            except ProtocolError as exc:
                raise ServiceError(f"{link.where}: {exc}") from None
        elif msg["t"] == "stats" and labels.complete:
            return labels.labels(), received, msg
        else:
            raise ServiceError(f"{link.where} sent {msg['t']} out of order")
