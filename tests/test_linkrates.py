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
from snail_common.net.linkrates import (
    MAX_AHEAD,
    Cycle,
    LinkRates,
    bytes_per_and,
    deeper,
    pick_scheme,
)
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


# the garbler's report and one n = 6 invocation under `region` (10 ms / 1 Gbit/s between
# the servers, 20 ms / 100 Mbit/s to the client), as the lab measured them: half-gates'
# 5.7 MB of tables take 48 ms on the link, three-halves' 4.4 MB 37 ms, and the client's
# own cycle, 42 ms of round trip and transfer plus the evaluation, 52 ms
REGION = {"and_per_s_halfgates": 27e6, "and_per_s_threehalves": 16e6, "link_mbit": 956.0}
NX_SIL_N6_AND = 177_347


def _cycle(scheme: str, other_s: float, evaluate_s: float, wait_s: float = 0.0) -> Cycle:
    cycle = Cycle(NX_SIL_N6_AND)
    for _ in range(3):
        cycle.invoked(scheme, other_s + evaluate_s + wait_s, evaluate_s + wait_s, wait_s)
    return cycle


def test_auto_keeps_half_gates_where_the_clients_cycle_outlasts_the_tables():
    """Three-halves' fewer bytes only pay where the link sets the pace: under `region` at
    n = 6 the client's own cycle is longer than either scheme's tables, and three-halves'
    slower evaluation lengthens it (the lab: 1.16 s per localization against
    half-gates' 1.05 s). Per AND gate alone the link looks like the limit."""
    assert pick_scheme(REGION) == "threehalves"  # no cycle measured: the link alone
    assert pick_scheme(REGION, _cycle("halfgates", 0.0425, 0.010)) == "halfgates"
    # measured under three-halves, its slower evaluation makes half-gates the faster
    assert pick_scheme(REGION, _cycle("threehalves", 0.0425, 0.017),
                       current="threehalves") == "halfgates"
    # a client next to the evaluator: the tables are the limit again, and every
    # evaluation waits for them
    assert pick_scheme(REGION, _cycle("halfgates", 0.002, 0.010, 0.035)) == "threehalves"


def test_auto_leaves_half_gates_only_once_evaluations_wait_for_tables():
    """The garbler's rate samples are rough (one stream's share, a tail): the service
    phase of a region run read the 1 Gbit/s link as 130-280 Mbit/s. A link that slow
    would make three-halves far faster, yet no evaluation waited for tables, so the
    link did not set the pace. Waits over a fifth of the time say it does; a session
    asked for just before its invocation waits whatever the link."""
    misread = {**REGION, "link_mbit": 200.0}
    assert pick_scheme(misread, _cycle("halfgates", 0.0425, 0.010)) == "halfgates"
    assert pick_scheme(misread, _cycle("halfgates", 0.0425, 0.010, 0.050)) == "threehalves"
    cold = Cycle(NX_SIL_N6_AND)  # a frame's first session, asked for just then
    cold.invoked("halfgates", 0.2, 0.16, 0.15, ahead_s=0.003)
    for _ in range(3):
        cold.invoked("halfgates", 0.0525, 0.010, 0.0, ahead_s=0.15)
    assert pick_scheme(misread, cold) == "halfgates"
    # side by side, sessions arrive in bunches: one waits for several, the next none
    bunched = Cycle(NX_SIL_N6_AND)
    for wait in (2.2, 0.0, 0.0, 3.7, 0.0, 0.0):
        bunched.invoked("halfgates", wait + 0.01, wait + 0.005, wait, ahead_s=1.0)
    assert pick_scheme(misread, bunched) == "threehalves"


def test_auto_tries_three_halves_where_tables_are_late_before_it_has_measured_it():
    """n = 256 over the paper's 2.5 Gbit/s server link: 193 MB of half-gates tables
    took 0.62 s and every evaluation waited for them (0.25 of 0.68 s). Three-halves'
    evaluation, guessed from half-gates' by the garbling rates (0.42 s x 1.67), hid its
    0.48 s of tables behind a 0.71 s cycle, and auto stayed on half-gates (0.68 s per
    iteration; three-halves ran 0.51-0.61 s). Untried, it goes by the link."""
    paper = {"and_per_s_halfgates": 28.7e6, "and_per_s_threehalves": 17.2e6,
             "link_mbit": 2391.0}
    n256 = Cycle(6_042_681)
    for _ in range(6):
        n256.invoked("halfgates", 0.68, 0.67, 0.25, ahead_s=1.4)
    assert pick_scheme(paper, n256) == "threehalves"
    # tables late, but the client's own cycle (42 ms round trip, 10 ms evaluation) is
    # longer than half-gates' 47 ms on the link: fewer bytes cannot make it sooner
    assert pick_scheme(REGION, _cycle("halfgates", 0.0425, 0.010, 0.050)) == "halfgates"
    # once it has run, its own measure decides (here: an evaluation slower by far)
    n256.invoked("threehalves", 1.2, 1.19, 0.0, ahead_s=1.4)
    assert pick_scheme(paper, n256, current="threehalves") == "halfgates"


def test_auto_does_not_switch_on_a_close_call():
    """Within SWITCH_GAIN of each other both schemes run at one pace: the scheme stays,
    in either direction."""
    near = _cycle("halfgates", 0.0425, 0.001)  # half-gates 48 ms of tables, three 44 ms
    assert pick_scheme(REGION, near) == "halfgates"
    assert pick_scheme(REGION, _cycle("threehalves", 0.0425, 0.006),  # half 2 % faster
                       current="threehalves") == "threehalves"


def test_an_evaluation_that_waited_for_tables_deepens_the_garble_ahead():
    """20 ms on every link: the rate and delay said one session ahead suffices, yet the
    window-limited stream brought an n = 6 session's tables 57 ms after they were sent
    and the evaluator waited 13-28 ms per invocation (+41 to +58 ms over unshaped)."""
    assert deeper(1, 0.013, 0.020) == 2 and deeper(2, 0.028, 0.020) == 3
    assert deeper(MAX_AHEAD, 0.05, 0.020) == MAX_AHEAD  # bounded: each holds memory
    assert deeper(1, 0.0005, 0.020) == 1  # a wait within noise keeps it


def test_a_wait_on_a_short_link_does_not_deepen_the_garble_ahead():
    """On loopback or a LAN a wait means busy servers, not a late stream: 16 clients on
    one pair all deepened to 3 and served fewer invocations per second."""
    assert deeper(1, 0.030, 0.0003) == 1 and deeper(2, 0.2, 0.001) == 2


def test_auto_is_half_gates_until_something_is_measured():
    assert pick_scheme(None) == "halfgates"
    assert pick_scheme({"and_per_s_halfgates": 2e6}) == "halfgates"


def test_three_halves_sends_fewer_bytes_per_and():
    assert bytes_per_and(SCHEME_HALF_GATES) == 32
    assert 24 < bytes_per_and(SCHEME_THREE_HALVES) < 25


def _info(rate: float, app_limited: bool, rtt_us: int = 10_000,
          unacked: int = 0) -> tcpinfo.TcpInfo:
    raw = bytearray(232)
    raw[7] = int(app_limited)
    struct.pack_into("=I", raw, 24, unacked)
    struct.pack_into("=I", raw, 68, rtt_us)
    struct.pack_into("=I", raw, 148, rtt_us)
    struct.pack_into("=Q", raw, 160, int(rate))
    info = tcpinfo.parse(bytes(raw))
    assert info is not None
    return info


def test_the_link_rate_is_the_median_of_recent_samples_of_the_whole_link():
    """A session's sample is its stream's share of the link: three sessions garbled
    ahead over a 50 Mbit/s link read 5-40 Mbit/s each, mostly 11. Scaled by the streams
    that shared the link, the median of recent samples keeps out both a stream's slow
    tail and a burst a token bucket let through."""
    rates = LinkRates()
    beside = [_info(1.4e6, app_limited=False, unacked=12)] * 2
    for rate in (1.4e6, 1.3e6, 1.5e6, 5e6, 1.4e6):  # bytes/s, each of three streams
        rates.streamed(_info(rate, app_limited=False), beside)
    assert rates.link_rate == pytest.approx(4.2e6)
    region = LinkRates()
    for mbit in (34.5, 936, 938, 1098, 957, 936, 782, 958):  # one stream, as measured
        region.streamed(_info(mbit * 1e6 / 8, app_limited=False))
    assert 900 < region.link_rate * 8 / 1e6 < 960


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


def test_a_stream_that_had_the_link_alone_reads_the_link_not_a_multiple():
    """n = 256 over a 2.5 Gbit/s link with two sessions garbled ahead: a stream's last
    samples, taken while the next sessions were still garbling, were the whole link;
    multiplied by the three sessions under way they read 5-16 Gbit/s, and auto saw no
    reason to send three-halves' fewer bytes. Streams that had nothing to send (app-
    limited), that are garbling their next frame (nothing in flight, whatever their last
    sample) or have gone add nothing; those sending beside it add their share."""
    link = 2.39e9 / 8
    alone = LinkRates()
    for _ in range(5):
        alone.streamed(_info(link, app_limited=False),
                       [_info(link / 3, app_limited=True, unacked=3), None,
                        _info(link / 2, app_limited=False)])
    assert alone.link_rate == pytest.approx(link)
    shared = LinkRates()
    for _ in range(5):
        shared.streamed(_info(link / 2, app_limited=False),
                        [_info(link / 2, app_limited=False, unacked=40)])
    assert shared.link_rate == pytest.approx(link)


def test_app_limited_bursts_do_not_raise_a_link_a_stream_has_met():
    """A shaper lets a burst through after an idle spell: three-halves at n = 256, its
    garbling slower than the 2.5 Gbit/s link, read 4-9 Gbit/s when app-limited samples
    could raise the estimate. They stand in only where no stream met the link."""
    link = 2.39e9 / 8
    rates = LinkRates()
    for _ in range(3):
        rates.streamed(_info(link, app_limited=False))
    for burst in (4e9, 7e9, 9e9, 5e9):
        rates.streamed(_info(burst / 8, app_limited=True))
    assert rates.link_rate == pytest.approx(link)
    loopback = LinkRates()  # the garbler is the limit: every sample app-limited
    for gbit in (8, 12, 10):
        loopback.streamed(_info(gbit * 1e9 / 8, app_limited=True))
    assert loopback.link_rate == pytest.approx(10e9 / 8)


def test_the_round_trip_follows_a_link_that_got_slower():
    """The lab's phases (and a stream moved to a farther replica) change the round trip
    under a garbler that has measured another: a minimum kept forever held the region
    profile's 20 ms link at the unshaped phase's 0.007 ms, and sized the garble-ahead
    for a link with no delay."""
    rates = LinkRates()
    for _ in range(3):
        rates.streamed(_info(10e9, app_limited=False, rtt_us=7))
    for _ in range(12):
        rates.streamed(_info(800e6, app_limited=False, rtt_us=20_000))
    assert rates.rtt_s == pytest.approx(0.02, rel=0.02)
    assert rates.link_rate == pytest.approx(800e6, rel=0.2)  # an EWMA: it gets there


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
