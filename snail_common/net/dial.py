"""TCP sockets for links of small bursts, set up before they connect.

A link with a client or a map owner at one end carries one small burst per invocation
(labels: a few to tens of kB) after an idle spell, and a round trip waits on it. BBR,
where it is the kernel's default, paces such a burst at the rate it estimated from the
earlier small bursts: ~10 ms for 11 kB at a 40 ms round trip. Those links therefore use
cubic, which sends a burst that fits the initial window at once (the kernel's choice
stays where cubic is not allowed). It is set before the connection exists: a socket that
started under BBR stays paced after a switch. Servers set it on their listening sockets
(their peers' bursts are small; the evaluator's end of the garbler's table stream only
acknowledges), clients and map owners on the sockets they connect (``dial_tcp``); the
garbler's connections to the evaluator, which carry the table stream, keep the kernel's
choice.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket

BURST_ROLES = ("client", "mapowner")  # links with one of these at an end: small bursts
BURST_CONGESTION = b"cubic"


def prefer_bursts(sock: socket.socket) -> None:
    """Cubic congestion control for a link of small bursts (module doc), where the kernel
    allows it; the kernel's choice otherwise."""
    if hasattr(socket, "TCP_CONGESTION"):
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_CONGESTION, BURST_CONGESTION)


async def dial_tcp(host: str, port: int) -> socket.socket:
    """A non-blocking socket connected to ``host``:``port``, set up for small bursts
    before it connected; each resolved address is tried in turn, the last failure raised
    (OSError) when none answers."""
    loop = asyncio.get_running_loop()
    failure: OSError = OSError(f"no address for {host}")
    for family, kind, proto, _, addr in await loop.getaddrinfo(host, port,
                                                               type=socket.SOCK_STREAM):
        sock = socket.socket(family, kind, proto)
        try:
            sock.setblocking(False)
            prefer_bursts(sock)
            await loop.sock_connect(sock, addr)
        except OSError as exc:
            sock.close()
            failure = exc
            continue
        except BaseException:
            sock.close()
            raise
        return sock
    raise failure
