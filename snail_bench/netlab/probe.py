"""What a link really does: TCP round-trip time and throughput between two namespaces.

``serve HOST PORT`` (in one namespace) answers two kinds of connection: ``p`` echoes every
byte back (a ping), ``b`` swallows a blast and replies with the bytes it got and the
seconds between the first and the last of them. ``measure HOST PORT`` (in the other)
pings ``--pings`` times and blasts for ``--seconds``, then prints one JSON object:
``{"rtt_ms": median, "rate_mbit": receiver's rate}``. TCP, because that is what the
daemons speak: the RTT includes no handshake. The rate is the link's once TCP has left
slow start: the blast lasts at least RAMP_RTTS round trips and the rate is taken over its
second half (a 1 s blast over the `continent` profile's 80 ms round trip read 314 of its
1,000 Mbit/s, and a localization's bound from it came out three times too long).
"""

from __future__ import annotations

import argparse
import json
import socket
import statistics
import sys
import time

CHUNK = 1 << 20
RAMP_RTTS = 25  # a blast lasts at least this many round trips: slow start ends in its first half


def serve(host: str, port: int) -> None:
    """Answer pings and blasts, one connection at a time, until killed."""
    listener = socket.create_server((host, port), reuse_port=False)
    print("ready", flush=True)
    while True:
        conn, _ = listener.accept()
        with conn:
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            kind = conn.recv(1)
            if kind == b"p":
                while data := conn.recv(64):
                    conn.sendall(data)
            elif kind == b"b":
                _swallow(conn)


def _swallow(conn: socket.socket) -> None:
    """Take a blast; reply with the bytes and seconds of its rate span (``rate_span``)."""
    buf = bytearray(CHUNK)
    arrivals: list[tuple[float, int]] = []  # (time, bytes so far after the first chunk)
    total = 0
    while got := conn.recv_into(buf):
        if arrivals:
            total += got
        arrivals.append((time.perf_counter(), total))
    span_bytes, span_s = rate_span(arrivals)
    conn.sendall(json.dumps({"bytes": span_bytes, "seconds": span_s}).encode())


def rate_span(arrivals: list[tuple[float, int]]) -> tuple[int, float]:
    """(bytes, seconds) a blast's rate is taken over, from its (time, bytes after the first
    chunk) arrivals: the second half of the span after the first chunk, once slow start is
    over; the whole span when its second half saw no arrival."""
    if len(arrivals) < 2:
        return 0, 0.0
    (first, _), (last, total) = arrivals[0], arrivals[-1]
    mid_t, mid_n = next((t, n) for t, n in arrivals if t >= (first + last) / 2)
    if last > mid_t:
        return total - mid_n, last - mid_t
    return total, last - first


def measure(host: str, port: int, pings: int, seconds: float) -> dict:
    """Median TCP ping RTT (ms) and receiver-side throughput (Mbit/s) to ``serve``."""
    with socket.create_connection((host, port), timeout=30) as conn:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.sendall(b"p")
        rtts = []
        for _ in range(pings):
            t0 = time.perf_counter()
            conn.sendall(b"x")
            if conn.recv(1) != b"x":
                raise ConnectionError("the probe's echo broke off")
            rtts.append((time.perf_counter() - t0) * 1000)
    with socket.create_connection((host, port), timeout=30) as conn:
        conn.sendall(b"b")
        payload = bytes(CHUNK)
        end = time.perf_counter() + max(seconds, RAMP_RTTS * statistics.median(rtts) / 1000)
        while time.perf_counter() < end:
            conn.sendall(payload)
        conn.shutdown(socket.SHUT_WR)
        reply = b""
        while data := conn.recv(4096):
            reply += data
    blast = json.loads(reply)
    rate = blast["bytes"] * 8 / 1e6 / blast["seconds"] if blast["seconds"] > 0 else 0.0
    return {"rtt_ms": round(statistics.median(rtts), 3), "rate_mbit": round(rate, 1)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    s = sub.add_parser("serve")
    m = sub.add_parser("measure")
    for p in (s, m):
        p.add_argument("host")
        p.add_argument("port", type=int)
    m.add_argument("--pings", type=int, default=10)
    m.add_argument("--seconds", type=float, default=1.0)
    args = parser.parse_args(argv)
    if args.command == "serve":
        serve(args.host, args.port)
    else:
        print(json.dumps(measure(args.host, args.port, args.pings, args.seconds)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
