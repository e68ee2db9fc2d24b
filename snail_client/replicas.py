"""A server role as the client reaches it: one ``NAME:PORT`` resolved to all its addresses,
each a replica (``tasks.garbler`` in a Docker swarm, a headless Kubernetes Service, or a
name with several A records), with a link to each replica in use.

Sessions are spread: every ``pick`` starts one replica further along the resolved list,
from a random first place, so a fleet of clients covers every replica and one client's
sessions take turns. A replica that refused a session as busy or draining, or whose link
broke, is passed over for ``SHUN_S`` seconds while another answers (the runner retries
the session there: secure.py); the name is resolved again at most every ``RESOLVE_TTL``
seconds, and at once when no replica answers (a rolling update moves every address).
"""

from __future__ import annotations

import asyncio
import secrets
import time
from collections.abc import Awaitable, Callable

from snail_common.net.conn import format_addr
from snail_common.net.errors import PEER_LOST, ConnectionClosed
from snail_common.net.replicas import RESOLVE_TTL, Address, resolve

from .links import Link, ServiceError

SHUN_S = 10.0  # a replica that failed a session is tried last for this long


class ReplicaSet:
    """The replicas of one role behind one address; ``open_link(addr)`` connects one."""

    def __init__(self, role: str, target: Address,
                 open_link: Callable[[Address], Awaitable[Link]]) -> None:
        self.role, self.target = role, target
        self.open_link = open_link
        self.links: dict[Address, Link] = {}
        self.shunned: dict[Address, float] = {}  # address -> until (monotonic)
        self._addresses: list[Address] = []
        self._resolved = -float("inf")
        self._turn = secrets.randbelow(1 << 16)  # fleets start spread over the replicas
        self._lock = asyncio.Lock()
        self.reached = False  # some replica answered once: losing them all is retryable

    @property
    def name(self) -> str:
        return format_addr(*self.target)

    async def addresses(self, fresh: bool = False) -> list[Address]:
        """What the name resolves to (cached RESOLVE_TTL seconds unless ``fresh``)."""
        if fresh or time.monotonic() - self._resolved > RESOLVE_TTL:
            try:
                self._addresses = await resolve(*self.target)
            except OSError as exc:
                if not self._addresses:
                    raise ServiceError(f"cannot resolve the {self.role} address "
                                       f"{self.name}: {exc}") from None
            self._resolved = time.monotonic()
        return list(self._addresses)

    async def pick(self) -> Link:
        """A live link to the next replica in turn, those shunned last; ServiceError when
        none answers (``peer_lost``, retryable while replicas come and go, once some
        replica of several had answered before)."""
        async with self._lock:
            failures: list[str] = []
            for fresh in (False, True):
                for addr in self._order(await self.addresses(fresh)):
                    link = self.links.get(addr)
                    if link is not None and link.reusable():
                        return link
                    try:
                        link = self.links[addr] = await self.open_link(addr)
                    except ConnectionClosed as exc:
                        self.links.pop(addr, None)
                        self.shun(addr)
                        failures.append(str(exc))
                        continue
                    self.reached = True
                    return link
            raise ServiceError(f"no {self.role} replica at {self.name} answers: "
                               f"{'; '.join(dict.fromkeys(failures)) or 'no address'}",
                               PEER_LOST if self.reached else None,
                               retry=self.reached and self.several())

    def _order(self, addrs: list[Address]) -> list[Address]:
        """The addresses from this turn's place on, those shunned now at the end."""
        if not addrs:
            return []
        self._turn += 1
        start = self._turn % len(addrs)
        turn = addrs[start:] + addrs[:start]
        now = time.monotonic()
        return ([a for a in turn if self.shunned.get(a, 0) <= now]
                + [a for a in turn if self.shunned.get(a, 0) > now])

    def shun(self, addr: Address, seconds: float = SHUN_S) -> None:
        """Pass over the replica at ``addr`` for ``seconds`` while others answer."""
        self.shunned[addr] = time.monotonic() + seconds

    def shun_link(self, link: Link, seconds: float = SHUN_S) -> None:
        """Shun the replica behind ``link`` (if it is one of this set's) for ``seconds``
        (for good: one caught cheating, audit.py)."""
        for addr, mine in self.links.items():
            if mine is link:
                self.shun(addr, seconds)

    def several(self) -> bool:
        """Whether the name stood for more than one replica when last resolved."""
        return len(self._addresses) > 1

    def any_link(self) -> Link | None:
        """A live link, if there is one (for health requests)."""
        return next((x for x in self.links.values() if x.reusable()), None)

    async def close(self) -> None:
        links, self.links = list(self.links.values()), {}
        await asyncio.gather(*(link.close() for link in links), return_exceptions=True)
