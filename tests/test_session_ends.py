"""A steady stream holds (issue 42): sessions garbled ahead are reservations that never
make a live run wait, and every way a session ends gives back what it held, descriptors
included (counted in /proc/PID/fd against the daemons' count at rest). Real daemons."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import ssl
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from daemons import daemons_with
from test_service_e2e import hello, raw, read_msg

from snail_client.secure import AsyncSecureRunner
from snail_common.circuit import evaluate_bits, registry
from snail_common.net import errors, messages, tls
from snail_common.net.conn import connect
from snail_common.net.frames import encode_bytes

CIRCUIT = "ops/fmul-x4"
REST_S = 6.0  # fds unchanged this long: at rest (pooled links close after 5 s unused)


def _fds(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


def _at_rest(svc, limit: float = 30.0) -> dict[str, int]:
    """Both daemons' fds once they have stopped changing for REST_S."""
    pids = {d.role: d.process.pid for d in (svc.garbler, svc.evaluator)}
    last, since, t0 = None, time.monotonic(), time.monotonic()
    while time.monotonic() - t0 < limit:
        now = {role: _fds(pid) for role, pid in pids.items()}
        if now != last:
            last, since = now, time.monotonic()
        elif time.monotonic() - since >= REST_S:
            return now
        time.sleep(0.25)
    raise AssertionError(f"the daemons' descriptors did not settle: {last}")


def _back_at_rest(svc, rest: dict[str, int], limit: float = 60.0) -> None:
    """Both daemons' fds back to their count at rest (a descriptor leaked never gets there;
    ``limit`` is a hang guard: pooled links close 5 s after their last use)."""
    pids = {d.role: d.process.pid for d in (svc.garbler, svc.evaluator)}
    deadline = time.monotonic() + limit
    while (now := {role: _fds(pid) for role, pid in pids.items()}) != rest:
        assert time.monotonic() < deadline, f"the daemons' descriptors: {now}, at rest {rest}"
        time.sleep(0.25)


def _sessions(log: Path) -> list[dict]:
    return [json.loads(x) for x in log.read_text().splitlines() if '"event": "session"' in x]


def _rows(k: int, seed: int = 3) -> np.ndarray:
    _, schedule = registry.compiled(CIRCUIT)
    return np.random.default_rng(seed).random((k, schedule.n_inputs)) < 0.5


@pytest.fixture(scope="module")
def services(tmp_path_factory):
    registry.compiled(CIRCUIT)
    yield from daemons_with(tmp_path_factory, "--max-sessions", "3", "--lane-window-ms", "0",
                            "--session-timeout", "3")


@pytest.fixture(scope="module")
def rest(services):
    """The daemons' descriptors at rest, after a first run (the circuit loaded)."""
    async def warm():
        async with AsyncSecureRunner(services.garbler_addr, services.evaluator_addr,
                                     services.tls_dir) as r:
            await r.invoke(CIRCUIT, _rows(1)[0])

    asyncio.run(warm())
    return _at_rest(services)


async def _holding(services, count: int, **kwargs) -> AsyncSecureRunner:
    """A client holding ``count`` sessions garbled ahead (reservations) on both daemons."""
    r = AsyncSecureRunner(services.garbler_addr, services.evaluator_addr, services.tls_dir,
                          ahead=count, **kwargs)
    await r.connect()
    r.expect(CIRCUIT, 100)
    deadline = time.monotonic() + 60  # a hang guard
    while len(r.ahead._prepared.get(CIRCUIT, ())) < count:
        assert time.monotonic() < deadline, "the reservations were never prepared"
        await asyncio.sleep(0.05)
    return r


def test_reservations_filling_the_cap_never_make_a_live_run_busy(services, rest):
    """Client A's pool holds every slot of both daemons (--max-sessions 3); client B's
    live run takes the place of one of A's reservations at once, without a single busy
    retry, and A's next runs still succeed (its pool re-plans)."""
    rows = _rows(4)
    want = evaluate_bits(registry.compiled(CIRCUIT)[1], rows)

    async def scenario():
        a = await _holding(services, 3)
        health = await a.health("evaluator")
        b = AsyncSecureRunner(services.garbler_addr, services.evaluator_addr,
                              services.tls_dir, busy_wait=0)
        try:
            live = await b.invoke(CIRCUIT, rows[0])
            after = [await a.invoke(CIRCUIT, row) for row in rows[1:]]
            counts = (await b.health("evaluator"))["sessions"]
        finally:
            await b.close()
            await a.close()
        return health, live, b.retries, after, counts

    health, live, retries, after, counts = asyncio.run(scenario())
    assert health["sessions"]["active"] == 3 and health["sessions"]["reserved"] == 3
    np.testing.assert_array_equal(live.outputs, want[0])
    assert retries == 0 and "client_busy_wait_s" not in live.timing
    for inv, expected in zip(after, want[1:]):
        np.testing.assert_array_equal(inv.outputs, expected)
    assert counts["evicted"] >= 1 and counts["busy"] == 0
    _back_at_rest(services, rest)


def test_a_client_told_busy_holds_fewer_ahead(tmp_path_factory):
    """Two reservations a client is refused (--max-ahead-per-peer 1): its pool drops to
    what the servers spare, and every run still succeeds."""
    svc_iter = daemons_with(tmp_path_factory, "--max-ahead-per-peer", "1",
                            "--lane-window-ms", "0")
    svc = next(svc_iter)
    rows = _rows(6, seed=5)
    try:
        async def scenario():
            async with AsyncSecureRunner(svc.garbler_addr, svc.evaluator_addr, svc.tls_dir,
                                         ahead=3) as r:
                r.expect(CIRCUIT, len(rows))
                runs = [await r.invoke(CIRCUIT, row) for row in rows]
                return runs, r.ahead.depth, r.retries

        runs, depth, retries = asyncio.run(scenario())
    finally:
        svc_iter.close()
    for inv, want in zip(runs, evaluate_bits(registry.compiled(CIRCUIT)[1], rows)):
        np.testing.assert_array_equal(inv.outputs, want)
    assert depth <= 1 and retries == 0


def test_sessions_cancelled_by_their_client_give_everything_back(services, rest):
    async def scenario():
        r = await _holding(services, 3)
        await r.close()  # cancels all three on both daemons
        async with AsyncSecureRunner(services.garbler_addr, services.evaluator_addr,
                                     services.tls_dir) as probe:
            await asyncio.sleep(0.5)
            return [(await probe.health(role))["sessions"] for role in ("garbler", "evaluator")]

    for counts in asyncio.run(scenario()):
        assert counts["active"] == 0 and counts["reserved"] == 0
    _back_at_rest(services, rest)


def test_a_killed_client_leaves_nothing_behind(services, rest):
    """A device that loses power with sessions garbled ahead (SIGKILL): both daemons drop
    them and every descriptor they held."""
    script = textwrap.dedent(f"""
        import asyncio, sys, time
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_session_ends import _holding
        class S: pass
        s = S(); s.garbler_addr, s.evaluator_addr, s.tls_dir = sys.argv[1:4]
        async def main():
            await _holding(s, 2)
            print("holding", flush=True)
            await asyncio.sleep(600)
        asyncio.run(main())
    """)
    proc = subprocess.Popen([sys.executable, "-c", script, services.garbler_addr,
                             services.evaluator_addr, str(services.tls_dir)],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "holding"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    _back_at_rest(services, rest)


def test_a_session_that_times_out_gives_everything_back(services, rest):
    """A client half whose garbler half never comes: failed after --session-timeout (3 s
    here), slot and all; the client's connection closes with it gone."""
    sid = os.urandom(16)
    with raw(services.evaluator_addr, services.tls_dir) as sock:
        hello(sock)
        sock.sendall(encode_bytes(messages.make(
            "session_start", sid=sid, circuit=CIRCUIT,
            hash=registry.compiled(CIRCUIT)[0].content_hash())))
        time.sleep(4)
    _back_at_rest(services, rest)
    line = next(s for s in _sessions(services.evaluator.log) if s["sid"] == sid.hex())
    assert line["outcome"] == errors.TIMEOUT


def test_a_client_half_of_a_session_that_already_ended_is_told_at_once(services, rest):
    """The garbler's half came first and its session ended (here: no client half within
    --session-timeout; an eviction alike): the client half that comes after is told why
    at once, not held waiting for a garbler half that has come and gone."""
    sid = os.urandom(16)
    start = dict(sid=sid, circuit=CIRCUIT, hash=registry.compiled(CIRCUIT)[0].content_hash())
    with raw(services.evaluator_addr, services.tls_dir, "garbler") as garbler:
        hello(garbler, "garbler")
        garbler.sendall(encode_bytes(messages.make("session_start", ahead=True, **start)))
        verdict = read_msg(garbler)  # after --session-timeout (3 s)
        assert verdict["t"] == "error" and verdict["sid"] == sid
        with raw(services.evaluator_addr, services.tls_dir) as client:
            hello(client)
            client.sendall(encode_bytes(messages.make("session_start", **start)))
            answer = read_msg(client)
    assert answer["t"] == "error" and answer["code"] == errors.TIMEOUT
    # the ended session's own reason: held waiting, the client half would have timed out
    # for want of a garbler half instead
    assert "the client's input labels did not arrive" in answer["message"]
    _back_at_rest(services, rest)


def test_a_connection_cancelled_while_it_opens_is_closed(tmp_path):
    """A session cancelled while its garbler was still opening its link to the evaluator
    (the server answered TLS, not yet its capabilities): that socket is closed with it.
    It stayed open before, one descriptor on each daemon every time."""
    tls_dir = tls.make_certs(tmp_path / "tls")
    accepted: list[asyncio.Transport] = []

    async def scenario() -> bool:
        loop = asyncio.get_running_loop()

        class Silent(asyncio.Protocol):  # takes the hello, never answers
            def connection_made(self, transport):
                accepted.append(transport)

        server = await loop.create_server(Silent, "127.0.0.1", 0,
                                          ssl=tls.server_context(tls_dir, "evaluator"))
        port = server.sockets[0].getsockname()[1]
        task = loop.create_task(connect("127.0.0.1", port, tls.client_context(
            tls_dir, "garbler"), "garbler", "evaluator", timeout=30))
        while not accepted:
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.2)  # the handshake is done, the hello sent
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        await asyncio.sleep(0.2)
        closed = accepted[0].is_closing() or _peer_gone(accepted[0])
        server.close()
        return closed

    assert asyncio.run(scenario()), "the cancelled connection is still open"


def _peer_gone(transport: asyncio.Transport) -> bool:
    sock = transport.get_extra_info("socket")
    try:
        return sock.recv(1, 0x40 | 0x2) == b""  # MSG_DONTWAIT | MSG_PEEK: EOF
    except (BlockingIOError, ssl.SSLError):
        return False
    except OSError:
        return True
