"""The replicas a server may dial: what its operator's ``NAME:PORT`` flags resolve to.

A server dials only addresses its own operator configured (the garbler's ``--evaluator``
and ``--map-owner``, the map owner's ``--evaluator``), never one a client names: else any
client could make it open connections where it likes (a server-side request forgery). A
configured name may stand for several replicas, as an orchestrator's DNS gives them
(``tasks.evaluator`` in a Docker swarm, a headless Service in Kubernetes), so a name is
resolved to all its addresses, again when asked for one it does not hold (replicas come
and go), and at most every ``ttl`` seconds otherwise. An address stays allowed for
RECENT_S after it left the answer: a draining replica leaves DNS before its sessions end.

A session must reach the one evaluator replica its client talks to. The client names it
twice: by the address it reached it at, and by the ``instance`` the replica announced in
its ``capabilities`` (a random id drawn at start, so a replica restarted on the same
address is a new one). ``locate`` takes the named address when the operator's names
resolve to it, and otherwise looks for the instance among the replicas they resolve to
(the client may reach the evaluator at another address than the servers do: separate
networks, NAT). A client-named host name is never resolved, and an address outside the
operator's names is never dialled: ``forbidden``, unless the instance is found on one
that is. The two operators share no state: the instance travels with the client's
request and is checked against what the garbler's own configuration resolves to.
"""

from __future__ import annotations

import asyncio
import ipaddress
import socket
import time
from collections.abc import Awaitable, Callable, Iterable

from .conn import Connection, format_addr, parse_addr
from .errors import BAD_REQUEST, FORBIDDEN, PEER_LOST, ConnectionClosed, ProtocolError

Address = tuple[str, int]
RESOLVE_TTL = 2.0  # seconds a resolution is reused when nothing new is asked for
# an address the names resolved to stays dialable this long after it left the answer: a
# replica that is draining has left DNS (a swarm drops a stopping task at once) while the
# sessions it admitted still need their table streams
RECENT_S = 600.0


def address_key(addr: Address) -> Address:
    """An address as allow-lists compare it: IP literals in one spelling (``::1`` is
    ``0:0::1``), host names in lower case."""
    host, port = addr
    try:
        return ipaddress.ip_address(host).compressed, port
    except ValueError:
        return host.lower(), port


def is_ip(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


async def resolve(host: str, port: int) -> list[Address]:
    """Every address ``host`` resolves to (in the resolver's order, each once); an IP
    literal is itself. OSError when the name does not resolve."""
    if is_ip(host):
        return [address_key((host, port))]
    infos = await asyncio.get_running_loop().getaddrinfo(host, port,
                                                         type=socket.SOCK_STREAM)
    found: list[Address] = []
    for *_, sockaddr in infos:
        key = address_key((sockaddr[0], sockaddr[1]))
        if key not in found:
            found.append(key)
    return found


class Replicas:
    """The addresses one role's configured names stand for, and the instance id each
    replica announced when this server last connected to it."""

    def __init__(self, names: Iterable[Address], flag: str, role: str,
                 ttl: float = RESOLVE_TTL) -> None:
        self.names = tuple(address_key(n) for n in names)
        self.flag, self.role, self.ttl = flag, role, ttl
        self.instances: dict[Address, str] = {}
        self._origin: dict[Address, str] = {}  # resolved address -> the name it came from
        self._seen: dict[Address, float] = {}  # resolved address -> when last resolved
        self._addresses: list[Address] = []
        self._resolved = -float("inf")
        self._lock = asyncio.Lock()

    def __bool__(self) -> bool:
        return bool(self.names)

    @property
    def configured(self) -> str:
        """The names as the operator gave them, for messages."""
        return ", ".join(f"{self.flag} {format_addr(*n)}" for n in self.names) \
            or f"no {self.flag}"

    async def addresses(self, fresh: bool = False) -> list[Address]:
        """What the names resolve to now (cached ``ttl`` seconds unless ``fresh``); a name
        that does not resolve (a service scaled to zero) adds nothing."""
        async with self._lock:
            if fresh or time.monotonic() - self._resolved > self.ttl:
                found: list[Address] = []
                for host, port in self.names:
                    try:
                        for addr in await resolve(host, port):
                            self._origin.setdefault(addr, host)
                            found += [addr] if addr not in found else []
                            self._seen[addr] = time.monotonic()
                    except OSError:
                        continue
                self._addresses, self._resolved = found, time.monotonic()
                self._seen = {a: t for a, t in self._seen.items()
                              if self._resolved - t < RECENT_S}
            return list(self._addresses)

    def server_name(self, addr: Address) -> str:
        """The name a replica's certificate must carry: the configured name its address
        was resolved from (replica addresses are not in certificates), else the host."""
        return self._origin.get(addr, addr[0])

    async def allowed(self, addr: Address) -> Address | None:
        """The configured name or resolved address ``addr`` is, if it is one (resolved
        afresh once, and those resolved within RECENT_S, before saying no); a client's
        host name is compared, not resolved."""
        key = address_key(addr)
        if key in self.names:
            return key
        if not is_ip(key[0]):
            return None
        for fresh in (False, True):
            if key in await self.addresses(fresh):
                return key
        # a replica the names resolved to lately (draining: gone from DNS, not yet away)
        seen = self._seen.get(key)
        return key if seen is not None and time.monotonic() - seen < RECENT_S else None

    async def check(self, named: str, field: str) -> Address:
        """The address a client named in ``field``, if the operator allowed it;
        ProtocolError (``forbidden``) before any connection otherwise."""
        addr = parse_named(named, field)
        key = await self.allowed(addr)
        if key is None:
            raise ProtocolError(FORBIDDEN, self._forbidden(field, named))
        return key

    def _forbidden(self, field: str, named: str) -> str:
        article = "an" if self.role[0] in "aeiou" else "a"
        return (f"field {field!r}: {named} is not {article} {self.role} this server may "
                f"dial (it dials only {self.configured}, as its operator allowed)")

    async def locate(self, named: str | None, instance: str | None, field: str,
                     take: Callable[[Address], Awaitable[Connection]],
                     give_back: Callable[[Address, Connection], None],
                     ) -> tuple[Address, Connection]:
        """A connection (from ``take``) to the replica the client named in ``field`` (its
        address) and by ``instance`` (see the module doc). Connections that turn out to
        reach another replica go to ``give_back``. ProtocolError: ``forbidden`` for an
        address outside the operator's names whose instance is not found on them either,
        ``peer_lost`` for an allowed one whose replica is gone (retryable elsewhere),
        ``bad_request`` when the request names no replica and there are several."""
        key = await self.allowed(parse_named(named, field)) if named is not None else None
        if named is not None and key is None and instance is None:
            raise ProtocolError(FORBIDDEN, self._forbidden(field, named))
        if named is None and instance is None:
            addrs = await self.addresses()
            if len(addrs) != 1:
                raise ProtocolError(BAD_REQUEST if addrs else PEER_LOST,
                                    f"field {field!r}: {self.configured} resolves to "
                                    f"{len(addrs)} replicas; the request must name the "
                                    f"one the client talks to")
            key = addrs[0]
        for fresh in (False, True):
            for addr in await self._candidates(key, instance, fresh):
                try:
                    conn = await take(addr)
                except ConnectionClosed:
                    self.instances.pop(addr, None)
                    continue
                got = conn.info.get("instance")
                if got is not None:
                    self.instances[addr] = got
                # a replica that announces no instance (an older build) is taken only
                # at the address the client named
                if instance is None or got == instance or (got is None and addr == key):
                    return addr, conn
                give_back(addr, conn)
        if key is None:
            raise ProtocolError(FORBIDDEN, self._forbidden(field, named or "?") +
                                f"; no replica of it is instance {instance}")
        raise ProtocolError(PEER_LOST, f"the {self.role} replica the client named "
                                       f"({named or format_addr(*key)}, instance "
                                       f"{instance}) is gone")

    async def _candidates(self, key: Address | None, instance: str | None,
                          fresh: bool) -> list[Address]:
        """Where to look: the named address first, then (for an instance) the replicas
        known to be it, then those not yet asked; on the second pass, all afresh."""
        if fresh:
            self.instances.clear()
        first = [key] if key is not None else []
        if instance is None:
            return first
        addrs = await self.addresses(fresh)
        known = [a for a in addrs if self.instances.get(a) == instance]
        unknown = [a for a in addrs if a not in self.instances]
        return list(dict.fromkeys([*first, *known, *unknown]))


def parse_named(named: str, field: str) -> Address:
    """A client-named HOST:PORT; ProtocolError (``bad_request``) naming the field."""
    try:
        return parse_addr(named)
    except ValueError as exc:
        raise ProtocolError(BAD_REQUEST, f"field {field!r}: {exc}") from None
