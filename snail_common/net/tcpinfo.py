"""What the kernel knows about a TCP connection (``TCP_INFO``, Linux): its round trip,
delivery rate and what limited it.

The garbler reads its table stream's connection after each session: the delivery rate
(when not limited by the garbler itself) is the server link's rate, measured on the
traffic that matters, and ``sndbuf_limited`` / ``rwnd_limited`` say whether a socket
buffer, not the link, held the stream back. Offsets are those of ``struct tcp_info``
(include/uapi/linux/tcp.h), stable since they were added; an older kernel returns a
shorter struct, and what it lacks reads as None.
"""

from __future__ import annotations

import socket
import struct
from dataclasses import dataclass

TCP_INFO = getattr(socket, "TCP_INFO", 11)
_SIZE = 232  # through tcpi_bytes_retrans and a little beyond
# name: (offset, struct format)
_FIELDS = {
    "unacked": (24, "I"), "rtt_us": (68, "I"), "snd_cwnd": (80, "I"), "total_retrans": (100, "I"),
    "min_rtt_us": (148, "I"), "delivery_rate": (160, "Q"), "busy_us": (168, "Q"),
    "rwnd_limited_us": (176, "Q"), "sndbuf_limited_us": (184, "Q"), "bytes_sent": (200, "Q"),
}


@dataclass(frozen=True)
class TcpInfo:
    """The fields snail uses; rates in bytes per second, times in seconds."""

    rtt_s: float
    min_rtt_s: float | None
    delivery_rate: float | None  # bytes/s of the last delivery sample
    app_limited: bool  # that sample was limited by the sender having nothing to send
    snd_cwnd: int
    busy_s: float | None
    rwnd_limited_s: float | None  # time the peer's receive window held the sender back
    sndbuf_limited_s: float | None  # time this side's send buffer held it back
    bytes_sent: int | None
    total_retrans: int
    unacked: int = 0  # segments in flight now: the connection is sending


def read(sock: socket.socket | None) -> TcpInfo | None:
    """The connection's TCP_INFO, or None where the platform has none or the connection
    has gone (a closed transport's ``get_extra_info("socket")`` is None: an evaluator
    replica that drained and exited right after answering failed the session here)."""
    if sock is None:
        return None
    try:
        raw = sock.getsockopt(socket.IPPROTO_TCP, TCP_INFO, _SIZE)
    except OSError:
        return None
    return parse(raw)


def parse(raw: bytes) -> TcpInfo | None:
    """``struct tcp_info`` bytes as a TcpInfo (None if too short to hold the RTT)."""
    values: dict[str, int | None] = {}
    for name, (offset, fmt) in _FIELDS.items():
        end = offset + struct.calcsize(fmt)
        values[name] = struct.unpack_from("=" + fmt, raw, offset)[0] if len(raw) >= end \
            else None
    if values["rtt_us"] is None or len(raw) < 8:
        return None

    def seconds(name: str) -> float | None:
        v = values[name]
        return None if v is None else v / 1e6

    return TcpInfo(rtt_s=values["rtt_us"] / 1e6, min_rtt_s=seconds("min_rtt_us"),
                   delivery_rate=None if values["delivery_rate"] is None
                   else float(values["delivery_rate"]),
                   app_limited=bool(raw[7] & 1), snd_cwnd=values["snd_cwnd"] or 0,
                   busy_s=seconds("busy_us"), rwnd_limited_s=seconds("rwnd_limited_us"),
                   sndbuf_limited_s=seconds("sndbuf_limited_us"),
                   bytes_sent=values["bytes_sent"], total_retrans=values["total_retrans"] or 0,
                   unacked=values["unacked"] or 0)


def host_setting(name: str) -> list[int] | None:
    """A ``net.ipv4`` sysctl of this host's network namespace as integers (None where
    /proc/sys does not have it): e.g. ``tcp_wmem`` (min, default, max bytes)."""
    try:
        return [int(x) for x in open(f"/proc/sys/net/ipv4/{name}").read().split()]
    except (OSError, ValueError):
        return None


def link_advice(link_rate: float | None, rtt_s: float | None) -> list[str]:
    """What this host's TCP settings cost a stream over a link of ``link_rate`` bytes/s
    and ``rtt_s`` round trips (the garbler logs it once): a send buffer under twice the
    bandwidth-delay product cannot fill the link, and a stream idle between sessions for
    longer than its retransmission timeout starts from a small window again."""
    advice: list[str] = []
    if not rtt_s or rtt_s < 0.001:  # one host or one rack: nothing here costs much
        return advice
    wmem = host_setting("tcp_wmem")
    if link_rate and rtt_s and wmem and wmem[2] < 2 * link_rate * rtt_s:
        advice.append(f"net.ipv4.tcp_wmem allows {wmem[2] / 1e6:.1f} MB of send buffer, "
                      f"under twice the link's bandwidth-delay product "
                      f"({2 * link_rate * rtt_s / 1e6:.1f} MB): raise its third value")
    idle = host_setting("tcp_slow_start_after_idle")
    if idle and idle[0] == 1:
        advice.append("net.ipv4.tcp_slow_start_after_idle=1: a table stream idle between "
                      "sessions restarts from a small window; set it to 0 on the servers")
    return advice
