"""The scheme a session gets from what the garbler measured (three-halves where the link,
not the garbler's CPU, is the limit) and the kernel's TCP_INFO as the garbler reads it."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import ssl
import struct
import threading

import pytest

from snail_common.gc.stream import SCHEME_HALF_GATES, SCHEME_THREE_HALVES
from snail_common.net import tcpinfo
from snail_common.net.conn import new_event_loop
from snail_common.net.linkrates import LinkRates, bytes_per_and, pick_scheme
from snail_common.net.tls import client_context, make_certs, server_context


def test_auto_picks_three_halves_on_a_link_slower_than_the_garbler():
    # half-gates at 2 M AND/s makes 64 MB/s (512 Mbit/s) of tables: a 100 Mbit/s link
    # is the limit, and three-halves' 24 B per AND beat its slower garbling
    slow_link = {"and_per_s_halfgates": 2e6, "and_per_s_threehalves": 0.8e6,
                 "link_mbit": 100.0}
    assert pick_scheme(slow_link) == "threehalves"
    assert pick_scheme({**slow_link, "link_mbit": 10_000.0}) == "halfgates"
    # the garbler's CPU is the limit at 1 Gbit/s: half-gates' faster garbling wins
    assert pick_scheme({**slow_link, "link_mbit": 1000.0}) == "halfgates"


def test_auto_is_half_gates_until_something_is_measured():
    assert pick_scheme(None) == "halfgates"
    assert pick_scheme({"and_per_s_halfgates": 2e6}) == "halfgates"


def test_three_halves_sends_fewer_bytes_per_and():
    assert bytes_per_and(SCHEME_HALF_GATES) == 32
    assert 24 < bytes_per_and(SCHEME_THREE_HALVES) < 25


def _info(rate: float, app_limited: bool, rtt_us: int = 10_000) -> tcpinfo.TcpInfo:
    raw = bytearray(232)
    raw[7] = int(app_limited)
    struct.pack_into("=I", raw, 68, rtt_us)
    struct.pack_into("=I", raw, 148, rtt_us)
    struct.pack_into("=Q", raw, 160, int(rate))
    info = tcpinfo.parse(bytes(raw))
    assert info is not None
    return info


def test_the_link_rate_comes_from_samples_the_garbler_did_not_limit():
    rates = LinkRates()
    rates.streamed(_info(50e6, app_limited=True))  # a lower bound: taken while unknown
    assert rates.link_rate == 50e6
    rates.streamed(_info(300e6, app_limited=False))
    assert 50e6 < rates.link_rate <= 300e6
    before = rates.link_rate
    rates.streamed(_info(10e6, app_limited=True))  # idle stream: says nothing new
    assert rates.link_rate == before and rates.rtt_s == pytest.approx(0.01)
    rates.garbled(SCHEME_HALF_GATES, 1_000_000, 0.5)
    report = rates.report()
    assert report["and_per_s_halfgates"] == 2_000_000
    assert report["and_per_s_threehalves"] < 2_000_000  # derived until measured
    assert report["link_rtt_ms"] == 10.0


def test_tcp_info_of_a_real_connection():
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def sink() -> None:
        conn, _ = server.accept()
        with conn:
            while conn.recv(1 << 20):
                pass

    thread = threading.Thread(target=sink)
    thread.start()
    with socket.create_connection(("127.0.0.1", port)) as sock:
        sock.sendall(bytes(4 << 20))
        info = tcpinfo.read(sock)
    thread.join(10)
    server.close()
    if info is None:
        pytest.skip("no TCP_INFO on this platform")
    assert info.rtt_s > 0 and info.snd_cwnd > 0
    assert info.bytes_sent is None or info.bytes_sent > 0  # retransmissions count too


def test_tcp_advice_only_for_a_real_network(monkeypatch):
    settings = {"tcp_wmem": [4096, 16384, 4 << 20], "tcp_slow_start_after_idle": [1]}
    monkeypatch.setattr(tcpinfo, "host_setting", settings.get)
    assert tcpinfo.link_advice(125e6, 0.0001) == []  # loopback, one rack
    advice = tcpinfo.link_advice(125e6, 0.08)  # 1 Gbit/s over 80 ms
    assert any("tcp_wmem" in a and "20.0 MB" in a for a in advice)
    assert any("tcp_slow_start_after_idle" in a for a in advice)
    settings.update(tcp_wmem=[4096, 16384, 32 << 20], tcp_slow_start_after_idle=[0])
    assert tcpinfo.link_advice(125e6, 0.08) == []


@pytest.mark.parametrize(("engine", "half_rate", "paper", "loopback"), [
    ("numpy", 7.9e6, "halfgates", "halfgates"),  # the garbler's CPU bounds either link
    ("native", 38e6, "threehalves", "halfgates"),  # 2.5 Gbit/s bounds half-gates' tables
])
def test_auto_follows_the_serving_engines_rates(engine, half_rate, paper, loopback):
    """A garbler derives three-halves' rate with its own engine's share until it has run
    both; the client's pick on the lab's paper link (2.5 Gbit/s) and on loopback then
    follows the engine that garbles (rates: snail-bench engine on this machine)."""
    rates = LinkRates.for_engine(engine)
    rates.garbled(SCHEME_HALF_GATES, int(half_rate), 1.0)
    report = rates.report()
    share = report["and_per_s_threehalves"] / report["and_per_s_halfgates"]
    assert share == pytest.approx({"numpy": 0.38, "native": 0.6}[engine], abs=0.01)
    assert pick_scheme({**report, "link_mbit": 2_500.0}) == paper
    assert pick_scheme({**report, "link_mbit": 40_000.0}) == loopback


def test_tcp_info_of_a_table_stream_that_has_gone_is_none(tmp_path):
    """The garbler reads TCP_INFO after the evaluator's answer; an evaluator replica that
    drained and exited right then left a TLS transport whose socket is None, and the
    session that had succeeded was failed as ``internal`` (deploy/swarm-test's rolling
    update, fresh-clone CI of 56fa563)."""
    tls_dir = make_certs(tmp_path / "tls")

    async def stream_then_gone():
        server = await asyncio.start_server(lambda r, w: w.close(), "127.0.0.1", 0,
                                            ssl=server_context(tls_dir, "evaluator"))
        port = server.sockets[0].getsockname()[1]
        _, writer = await asyncio.open_connection(
            "127.0.0.1", port, ssl=client_context(tls_dir, "garbler"),
            server_hostname="localhost")
        live = tcpinfo.read(writer.transport.get_extra_info("socket"))
        writer.close()
        with contextlib.suppress(OSError, ssl.SSLError):
            await writer.wait_closed()
        server.close()
        await server.wait_closed()
        return live, writer.transport.get_extra_info("socket")

    loop = new_event_loop()  # uvloop, as the daemons run
    try:
        live, gone = loop.run_until_complete(stream_then_gone())
    finally:
        loop.close()
    assert live is not None and live.rtt_s >= 0
    assert gone is None and tcpinfo.read(gone) is None
