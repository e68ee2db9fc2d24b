"""The lab's wire: delay, jitter and loss on each link, packet by packet.

The lab runs the same forwarder in C (``wire.c``, built by ``wire_native.py``) wherever a
C compiler works; this one is the fallback, and the netem JSON says which ran: it costs
about four times the CPU per byte (a zero-delay blast saturates it near 1.5 Gbit/s where
the C wire passes 6), which shows in the control run.

This kernel has no ``sch_netem`` (nor fq or etf, which could honour a departure time), so
the lab delays packets in user space: every link runs through a middle namespace as two
veth pairs, ``A <-> a_side | wire | b_side <-> B``, and this process copies each Ethernet
frame from one side to the other once its time has come. Rate stays with the kernel (tbf
on the endpoints). Frames carry their virtio-net header (``PACKET_VNET_HDR``), so a TCP
segment offloaded as one 64 KiB frame with a partial checksum crosses the wire as it was
sent: no per-MTU copying in Python, no checksum rewriting.

Each direction keeps its own FIFO with departures that never go backwards: jitter delays
packets but does not reorder them (netem's default with a rate, and what TCP expects of a
link). Loss drops a frame with the given probability before it enters the queue.

Run as ``python -m snail_bench.netlab.wire --link A_IF,B_IF,DELAY_MS,JITTER_MS,LOSS_PCT ...``
inside the middle namespace; it prints ``ready`` once every socket is bound and runs until
SIGTERM or SIGINT.
"""

from __future__ import annotations

import argparse
import random
import select
import signal
import socket
import sys
import time
from collections import deque
from dataclasses import dataclass, field

ETH_P_ALL = 0x0003
SOL_PACKET = 263
PACKET_VNET_HDR = 15
PACKET_IGNORE_OUTGOING = 23
FRAME_MAX = 65536 + 64  # a GSO frame plus the virtio-net header
BURST = 64  # frames read from one socket per wake-up
SOCKET_BUFFER = 8 << 20  # bursts of 64 KiB frames while this process is descheduled
SO_SNDBUFFORCE, SO_RCVBUFFORCE = 32, 33  # root may exceed net.core.[rw]mem_max


@dataclass
class Direction:
    """Frames from one side waiting for their departure to the other."""

    out: socket.socket
    delay_s: float
    jitter_s: float
    loss: float
    queue: deque[tuple[float, bytes]] = field(default_factory=deque)
    last_due: float = 0.0

    def admit(self, frame: bytes, now: float, rng: random.Random) -> None:
        if self.loss and rng.random() < self.loss:
            return
        due = now + self.delay_s
        if self.jitter_s:
            due += rng.uniform(-self.jitter_s, self.jitter_s)
        self.last_due = max(due, self.last_due)
        self.queue.append((self.last_due, frame))

    def flush(self, now: float) -> float | None:
        """Send every frame that is due; the next departure time, if any."""
        queue = self.queue
        while queue and queue[0][0] <= now:
            try:
                self.out.send(queue[0][1])
            except BlockingIOError:
                return now + 0.0005  # the device queue is full: try again shortly
            except OSError:
                pass  # a frame the device refuses is lost, as on a wire
            queue.popleft()
        return queue[0][0] if queue else None


def packet_socket(ifname: str) -> socket.socket:
    """A raw socket on ``ifname`` that sees every frame arriving (not its own sends)."""
    sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
    sock.setsockopt(SOL_PACKET, PACKET_VNET_HDR, 1)
    sock.setsockopt(SOL_PACKET, PACKET_IGNORE_OUTGOING, 1)
    sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, SOCKET_BUFFER)
    sock.setsockopt(socket.SOL_SOCKET, SO_SNDBUFFORCE, SOCKET_BUFFER)
    sock.bind((ifname, ETH_P_ALL))
    sock.setblocking(False)
    return sock


def parse_link(text: str) -> tuple[str, str, float, float, float]:
    """``A_IF,B_IF,DELAY_MS,JITTER_MS,LOSS_PCT`` -> names, seconds, seconds, fraction."""
    a, b, delay, jitter, loss = text.split(",")
    return a, b, float(delay) / 1000, float(jitter) / 1000, float(loss) / 100


def run(links: list[tuple[str, str, float, float, float]]) -> None:
    """Forward frames on every link until SIGTERM/SIGINT."""
    routes: dict[int, tuple[socket.socket, Direction]] = {}
    directions: list[Direction] = []
    for a, b, delay, jitter, loss in links:
        sa, sb = packet_socket(a), packet_socket(b)
        for src, dst in ((sa, sb), (sb, sa)):
            direction = Direction(dst, delay, jitter, loss)
            routes[src.fileno()] = (src, direction)
            directions.append(direction)
    poller = select.poll()
    for fd in routes:
        poller.register(fd, select.POLLIN)
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    rng = random.Random()
    print("ready", flush=True)
    next_due: float | None = None
    while not stop:
        timeout = None if next_due is None else max(0, (next_due - time.monotonic()) * 1000)
        try:
            events = poller.poll(timeout if timeout is None else int(timeout) + 1)
        except InterruptedError:
            continue
        now = time.monotonic()
        for fd, _ in events:
            src, direction = routes[fd]
            for _ in range(BURST):
                try:
                    frame = src.recv(FRAME_MAX)
                except BlockingIOError:
                    break
                direction.admit(frame, now, rng)
        now = time.monotonic()
        dues = [d for d in (direction.flush(now) for direction in directions) if d is not None]
        next_due = min(dues, default=None)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--link", action="append", required=True, type=parse_link,
                        metavar="A_IF,B_IF,DELAY_MS,JITTER_MS,LOSS_PCT")
    run(parser.parse_args(argv).link)
    return 0


if __name__ == "__main__":
    sys.exit(main())
