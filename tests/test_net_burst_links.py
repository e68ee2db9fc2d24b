"""Links with a client at one end use cubic congestion control from their first packet
(dial.py module doc: BBR paces a small burst after idle over a good part of a round
trip, and a socket that started under BBR stays paced); the garbler's table stream to
the evaluator keeps the kernel's choice."""

from __future__ import annotations

import asyncio
import shutil
import socket
import subprocess

import numpy as np
import pytest

from snail_client.secure import AsyncSecureRunner
from snail_common.circuit import registry
from snail_common.net.conn import parse_addr
from snail_common.net.dial import BURST_CONGESTION, prefer_bursts
from tests.daemons import daemons_with

CIRCUIT = "ops/fmul-x4"


def _congestion(sock) -> bytes:
    return sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_CONGESTION, 16).rstrip(b"\0")


def _kernel_default() -> bytes:
    with open("/proc/sys/net/ipv4/tcp_congestion_control", "rb") as f:
        return f.read().strip()


pytestmark = pytest.mark.skipif(not hasattr(socket, "TCP_CONGESTION"),
                                reason="no TCP_CONGESTION socket option on this platform")


def test_prefer_bursts_sets_cubic_on_the_socket():
    with socket.socket() as probe:
        if _congestion(probe) == BURST_CONGESTION:
            probe.setsockopt(socket.IPPROTO_TCP, socket.TCP_CONGESTION, b"reno")
            assert _congestion(probe) == b"reno"  # a change can be seen at all
        prefer_bursts(probe)
        assert _congestion(probe) == BURST_CONGESTION


@pytest.fixture(scope="module")
def services(tmp_path_factory):
    yield from daemons_with(tmp_path_factory)


def _ss_congestion(port: int) -> dict[tuple[int, int], str]:
    """(local port, peer port) -> congestion control of every established TCP socket
    with ``port`` at one end, as `ss -ti` reports it."""
    out = subprocess.run(["ss", "-tinH", "state", "established"], capture_output=True,
                         text=True, check=True).stdout.splitlines()
    found = {}
    for addresses, details in zip(out[::2], out[1::2], strict=False):
        fields = addresses.split()
        local, peer = (int(x.rsplit(":", 1)[1]) for x in fields[-2:])
        if port in (local, peer):
            names = [w for w in details.split() if w in ("cubic", "bbr", "reno")]
            found[local, peer] = names[0] if names else "?"
    return found


def test_a_clients_links_are_cubic_at_both_ends_and_the_table_stream_is_not(services):
    if shutil.which("ss") is None:
        pytest.skip("no `ss` (iproute2) to read the servers' sockets")
    n = registry.compiled(CIRCUIT)[1].n_inputs

    async def scenario():
        async with AsyncSecureRunner(services.garbler_addr, services.evaluator_addr,
                                     services.tls_dir, timeout=60) as r:
            await r.invoke(CIRCUIT, np.zeros(n, bool))
            links = {role: r.replicas[role].any_link().conn.transport.get_extra_info("socket")
                     for role in ("garbler", "evaluator")}
            ports = {role: s.getsockname()[1] for role, s in links.items()}
            mine = {role: _congestion(s) for role, s in links.items()}
            return ports, mine, _ss_congestion(parse_addr(services.evaluator_addr)[1])

    ports, mine, seen = asyncio.run(scenario())
    cubic, kernel = BURST_CONGESTION.decode(), _kernel_default().decode()
    assert mine == {"garbler": BURST_CONGESTION, "evaluator": BURST_CONGESTION}
    evaluator_port = parse_addr(services.evaluator_addr)[1]
    assert seen[evaluator_port, ports["evaluator"]] == cubic  # the evaluator's end
    garbler_ends = [cc for (local, peer), cc in seen.items()
                    if peer == evaluator_port and local not in ports.values()]
    assert garbler_ends and all(cc == kernel for cc in garbler_ends)  # the table stream
