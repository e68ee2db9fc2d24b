"""The three roles as real processes on loopback over mutually authenticated TLS 1.3.

One evaluator and garbler pair serves the module; tests that kill or stop a daemon start
their own. Every rejection test ends by checking the daemons still serve.
"""

import asyncio
import contextlib
import json
import socket
import ssl
import struct
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from table_floor import per_and

from snail_client.blocking import SecureRunner
from snail_client.embedded import embedded_services, start_daemon
from snail_client.links import ServiceError
from snail_client.secure import AsyncSecureRunner
from snail_client.sessions import LINKS
from snail_common.circuit import encode_inputs, evaluate_bits, registry
from snail_common.net import errors, messages, tls
from snail_common.net.conn import new_event_loop, parse_addr
from snail_common.net.frames import PROTOCOL_VERSION, decode, encode_bytes

SID = bytes(range(16))
T = TypeVar("T")


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    path = tmp_path_factory.mktemp("cache")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SNAIL_CACHE_DIR", str(path))
        yield path


@pytest.fixture(scope="module")
def services(cache):
    with embedded_services(log_level="info", env={"SNAIL_CACHE_DIR": str(cache)}) as svc:
        yield svc


@pytest.fixture(scope="module")
def runner(services):
    with SecureRunner(services.garbler_addr, services.evaluator_addr, services.tls_dir,
                      timeout=60) as r:
        yield r


def cleartext(circuit_id: str, bits: np.ndarray) -> np.ndarray:
    _, schedule = registry.compiled(circuit_id)
    return evaluate_bits(schedule, bits[None])[0]


def float_bits(circuit_id: str, values: dict) -> np.ndarray:
    circuit, _ = registry.compiled(circuit_id)
    return encode_inputs(circuit, values)[0]


def wait_for(probe: Callable[[], T], done: Callable[[T], bool], timeout: float = 60.0) -> None:
    """Poll ``probe`` until ``done`` holds of its value: what a server does after the
    client has heard the outcome (freeing a session) happens a moment later. ``timeout``
    only guards against a hang: far beyond what a loaded core takes."""
    deadline = time.monotonic() + timeout
    while not done(value := probe()):
        assert time.monotonic() < deadline, f"not within {timeout:g} s: {value}"
        time.sleep(0.05)


def assert_still_serves(runner: SecureRunner) -> None:
    bits = np.random.default_rng(0).random(64) < 0.5
    np.testing.assert_array_equal(runner.run("ops/fadd-x1", bits),
                                  cleartext("ops/fadd-x1", bits))


# ---- results ---------------------------------------------------------------------------
floats = st.floats(-1e6, 1e6, width=32, allow_subnormal=False)


@settings(max_examples=6, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.sampled_from(["ops/fadd-x4", "ops/fmul-x4", "ops/flt-x4"]),
       st.lists(floats, min_size=8, max_size=8))
def test_ops_are_bit_identical_to_cleartext(runner, op, values):
    v = np.array(values, np.float32)
    bits = float_bits(op, {"x": v[:4], "y": v[4:]})
    np.testing.assert_array_equal(runner.run(op, bits), cleartext(op, bits))


def test_traffic_and_time_are_measured(runner):
    circuit, schedule = registry.compiled("ops/fmul-x4")
    bits = np.random.default_rng(1).random(schedule.n_inputs) < 0.5
    inv = runner.invoke("ops/fmul-x4", bits)
    np.testing.assert_array_equal(inv.outputs, cleartext("ops/fmul-x4", bits))
    t = inv.traffic
    assert set(t) == set(LINKS)
    assert t["garbler_to_evaluator"] >= per_and(inv.scheme) * schedule.n_and
    assert t["client_to_evaluator"] >= 16 * (schedule.n_inputs + 2)
    assert t["evaluator_to_client"] >= 16 * circuit.n_outputs
    assert t["garbler_to_client"] >= 16 * circuit.n_outputs
    assert 48 < t["client_to_garbler"] < 400  # seed, delta, key and the circuit name
    assert inv.wall_s > 0
    assert inv.timing["garbler_garble_s"] > 0 and inv.timing["evaluator_evaluate_s"] > 0


def test_expected_runs_are_garbled_before_their_inputs_exist(services):
    """After ``expect``, the evaluator holds a session's whole table stream before the
    client's labels arrive; each prepared session runs once with its own secrets."""
    _, schedule = registry.compiled("ops/fmul-x4")
    rng = np.random.default_rng(7)

    async def scenario():
        async with AsyncSecureRunner(services.garbler_addr, services.evaluator_addr,
                                     services.tls_dir, timeout=60, ahead=2) as r:
            r.expect("ops/fmul-x4", 3)
            await asyncio.sleep(1.0)  # both prepared sessions garble meanwhile
            runs = []
            for _ in range(3):
                bits = rng.random(schedule.n_inputs) < 0.5
                runs.append((bits, await r.invoke("ops/fmul-x4", bits)))
            return runs, r.ahead._prepared["ops/fmul-x4"]

    runs, left = asyncio.run(scenario())
    for bits, inv in runs:
        np.testing.assert_array_equal(inv.outputs, cleartext("ops/fmul-x4", bits))
    # all of it, before the labels
    assert runs[0][1].garbled_ahead >= per_and(runs[0][1].scheme) * schedule.n_and
    assert not left  # none prepared beyond the three announced


def test_two_clients_at_once_get_their_own_results(services):
    ids = ["ops/fadd-x8", "ops/fmul-x8", "ops/fsub-x8"]
    rng = np.random.default_rng(2)
    jobs = [(cid, rng.random(registry.compiled(cid)[1].n_inputs) < 0.5)
            for cid in ids for _ in range(2)]

    async def client(work):
        async with AsyncSecureRunner(services.garbler_addr, services.evaluator_addr,
                                     services.tls_dir, timeout=60) as r:
            # several invocations in flight on the same two connections, too
            return await asyncio.gather(*(r.run(cid, bits) for cid, bits in work))

    async def both():
        return await asyncio.gather(client(jobs[:3]), client(jobs[3:]))

    first, second = new_event_loop().run_until_complete(both())
    for (cid, bits), out in zip(jobs, [*first, *second]):
        np.testing.assert_array_equal(out, cleartext(cid, bits))


def _watcher_and_client(services, garbler_addr: str):
    """A runner that asks the services for health, and one that runs sessions through the
    garbler at ``garbler_addr``."""
    return (AsyncSecureRunner(services.garbler_addr, services.evaluator_addr,
                              services.tls_dir),
            AsyncSecureRunner(garbler_addr, services.evaluator_addr, services.tls_dir,
                              timeout=60))


def test_the_garblers_streaming_gauge_counts_streams_under_way(services, runner):
    circuit_id = "ops/fmul-x1024"  # ~1 M AND: long enough to be seen mid-stream
    _, schedule = registry.compiled(circuit_id)
    bits = np.random.default_rng(5).random(schedule.n_inputs) < 0.5

    async def scenario():
        watcher, client = _watcher_and_client(services, services.garbler_addr)
        try:
            task = asyncio.ensure_future(client.run(circuit_id, bits))
            seen = 0
            while not task.done():
                seen = max(seen, (await watcher.health("garbler"))["sessions"]["streaming"])
                await asyncio.sleep(0.001)
            await task
            return seen, (await watcher.health("garbler"))["sessions"]["streaming"]
        finally:
            await asyncio.gather(client.close(), watcher.close())

    seen, after = new_event_loop().run_until_complete(scenario())
    assert (seen, after) == (1, 0)


# ---- failures --------------------------------------------------------------------------
def test_killed_garbler_gives_a_clear_error_and_frees_the_session(services, runner, cache,
                                                                   tmp_path):
    circuit_id = "ops/fmul-x1024"  # ~1 M AND: long enough to be caught mid-stream
    _, schedule = registry.compiled(circuit_id)  # on disk before the daemons need it
    victim = start_daemon("garbler", ["--evaluator", services.evaluator_addr, "--tls-dir",
                                      str(services.tls_dir)], tmp_path / "victim.log",
                          env={"SNAIL_CACHE_DIR": str(cache)})
    bits = np.random.default_rng(3).random(schedule.n_inputs) < 0.5
    before = runner.health("evaluator")["sessions"]

    async def scenario():
        watcher, client = _watcher_and_client(services, victim.address)
        try:
            task = asyncio.ensure_future(client.run(circuit_id, bits))
            while (await watcher.health("evaluator"))["sessions"]["streaming"] == 0:
                assert not task.done(), "the run ended before the garbler could be killed"
                await asyncio.sleep(0.001)
            victim.process.kill()
            with pytest.raises(ServiceError, match="garbler") as info:
                await task
            return str(info.value)
        finally:
            await asyncio.gather(client.close(), watcher.close())

    try:
        message = new_event_loop().run_until_complete(scenario())
    finally:
        victim.stop()
    assert "no result within" not in message  # the lost link's error, not the timeout's
    wait_for(lambda: runner.health("evaluator")["sessions"],
             lambda now: (now["active"], now["failed"]) == (before["active"],
                                                            before["failed"] + 1))
    assert_still_serves(runner)


def raw(addr: str, tls_dir, role: str = "client", ctx: ssl.SSLContext | None = None):
    host, port = parse_addr(addr)
    ctx = ctx or tls.client_context(tls_dir, role)
    sock = ctx.wrap_socket(socket.create_connection((host, port), timeout=10),
                           server_hostname=host)
    sock.settimeout(10)
    return sock


def read_msg(sock) -> dict | None:
    """The next message, or None at EOF."""
    def exactly(n):
        data = b""
        while len(data) < n:
            chunk = sock.recv(n - len(data))
            if not chunk:
                return None
            data += chunk
        return data
    head = exactly(4)
    if head is None:
        return None
    return decode(exactly(struct.unpack(">I", head)[0]))


def hello(sock, role: str = "client") -> dict:
    sock.sendall(encode_bytes(messages.make("hello", role=role, software="test",
                                            max_frame=1 << 20)))
    return read_msg(sock)


def frame(obj) -> bytes:
    data = obj if isinstance(obj, bytes) else msgpack.packb(obj, use_bin_type=True)
    return struct.pack(">I", len(data)) + data


BAD_FRAMES = [
    (struct.pack(">I", 1 << 30), errors.OVERSIZE),
    (frame(b"\xc1\xc1\xc1"), errors.MALFORMED),
    (frame({"v": PROTOCOL_VERSION + 1, "t": "health_request"}), errors.VERSION),
    (frame({"v": PROTOCOL_VERSION, "t": "launch"}), errors.UNKNOWN_TYPE),
    (frame({"v": PROTOCOL_VERSION, "t": "session_start", "sid": SID}),
     errors.MISSING_FIELD),
]


@pytest.mark.parametrize("role", ["garbler", "evaluator"])
@pytest.mark.parametrize("data, code", BAD_FRAMES,
                         ids=["oversize", "garbage", "version", "unknown_type", "missing"])
def test_bad_frames_are_rejected_and_the_daemon_lives_on(services, runner, role, data, code):
    addr = services.garbler_addr if role == "garbler" else services.evaluator_addr
    for after_hello in (False, True):
        with contextlib.closing(raw(addr, services.tls_dir)) as sock:
            if after_hello:
                assert hello(sock)["t"] == "capabilities"
            sock.sendall(data)
            reply = read_msg(sock)
            assert reply is not None and reply["t"] == "error" and reply["code"] == code
            assert read_msg(sock) is None  # and the connection is closed
    assert runner.health(role)["role"] == role
    assert_still_serves(runner)


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def test_forty_frames_of_millions_of_tiny_objects_pin_no_memory(services, runner):
    """Each 4 MiB frame is four million empty maps: the evaluator refuses each while it
    has decoded a handful, keeps nothing of it, and answers a fresh client at once."""
    body = b"\xdd" + (4_000_000).to_bytes(4, "big") + b"\x80" * 4_000_000
    bomb = struct.pack(">I", len(body)) + body
    socks = []
    before = _rss_mb(services.evaluator.process.pid)
    try:
        for _ in range(40):
            sock = raw(services.evaluator_addr, services.tls_dir)
            socks.append(sock)
            assert hello(sock)["t"] == "capabilities"
            sock.sendall(bomb)
            reply = read_msg(sock)
            assert reply is not None and reply["code"] == errors.MALFORMED
        grew = _rss_mb(services.evaluator.process.pid) - before
        # ~6 MB a connection the peer keeps open (TLS and socket buffers); decoded, it
        # was ~90 MB a frame (3.5 GB for the forty)
        assert grew < 350, f"40 refused frames left {grew:.0f} MB behind"
        assert_still_serves(runner)
    finally:
        for sock in socks:
            sock.close()


def test_unknown_circuit_is_refused_per_session(services, runner):
    with pytest.raises(ServiceError, match="unknown op"):
        runner.run("ops/fnope-x1", np.zeros(64, bool))
    start = dict(sid=SID, circuit="ops/fnope-x1", hash="0" * 64)
    for addr, msg in [
        (services.garbler_addr, messages.make("garble_request", **start, seed=bytes(16),
                                              delta=b"\x01" + bytes(15), key=bytes(16))),
        (services.evaluator_addr, messages.make("session_start", **start)),
    ]:
        with contextlib.closing(raw(addr, services.tls_dir)) as sock:
            hello(sock)
            sock.sendall(encode_bytes(msg))
            reply = read_msg(sock)
            assert (reply["t"], reply["code"], reply["sid"]) == (
                "error", errors.UNKNOWN_CIRCUIT, SID)
            assert "fnope" in reply["message"]
            sock.sendall(encode_bytes(messages.make("health_request")))  # still open
            assert read_msg(sock)["t"] == "health"
    assert_still_serves(runner)


def test_wrong_hash_and_bad_delta_are_refused(services, runner):
    circuit, _ = registry.compiled("ops/fadd-x1")
    good = dict(sid=SID, circuit="ops/fadd-x1", hash=circuit.content_hash())
    cases = [(dict(good, hash="0" * 64, delta=b"\x01" + bytes(15)), errors.CIRCUIT_MISMATCH),
             (dict(good, delta=bytes(16)), errors.BAD_REQUEST)]
    with contextlib.closing(raw(services.garbler_addr, services.tls_dir)) as sock:
        hello(sock)
        for fields, code in cases:
            sock.sendall(encode_bytes(messages.make("garble_request", seed=bytes(16),
                                                    key=bytes(16), **fields)))
            reply = read_msg(sock)
            assert (reply["t"], reply["code"]) == ("error", code)
    assert_still_serves(runner)


def test_a_wrong_hash_is_refused_before_anything_is_compiled(services, runner, cache):
    """The garbler checks the hash on the circuit's interface first: a request for a
    circuit it never compiled, with a wrong hash, leaves no compiled entry behind."""
    circuit_id = "ops/fsub-x3"
    before = set(cache.glob("ops-fsub-x3.*.arrays"))
    with contextlib.closing(raw(services.garbler_addr, services.tls_dir)) as sock:
        hello(sock)
        sock.sendall(encode_bytes(messages.make(
            "garble_request", sid=SID, circuit=circuit_id, hash="0" * 64, seed=bytes(16),
            delta=b"\x01" + bytes(15), key=bytes(16))))
        reply = read_msg(sock)
    assert (reply["t"], reply["code"]) == ("error", errors.CIRCUIT_MISMATCH)
    assert set(cache.glob("ops-fsub-x3.*.arrays")) == before == set()
    assert_still_serves(runner)


def test_roles_come_from_certificates(services, runner):
    # a client certificate cannot pass for the garbler ...
    with contextlib.closing(raw(services.evaluator_addr, services.tls_dir)) as sock:
        reply = hello(sock, role="garbler")
        assert (reply["t"], reply["code"]) == ("error", errors.FORBIDDEN)
    # ... nor stream tables, nor hand the garbler input labels
    for addr, msg in [
        (services.evaluator_addr, messages.make("tables", sid=SID, data=bytes(32))),
        (services.garbler_addr, messages.make("input_labels", sid=SID, start=0, total=1,
                                              labels=bytes(16))),
    ]:
        with contextlib.closing(raw(addr, services.tls_dir)) as sock:
            hello(sock)
            sock.sendall(encode_bytes(msg))
            reply = read_msg(sock)
            assert (reply["t"], reply["code"]) == ("error", errors.UNEXPECTED)
    # the garbler's certificate may not talk to the garbler as a client
    with contextlib.closing(raw(services.garbler_addr, services.tls_dir, role="garbler")) \
            as sock:
        reply = hello(sock, role="garbler")
        assert (reply["t"], reply["code"]) == ("error", errors.FORBIDDEN)
    # a client given swapped addresses never sends its seed to the evaluator
    swapped = SecureRunner(services.evaluator_addr, services.garbler_addr, services.tls_dir)
    with pytest.raises(ServiceError, match="expected the garbler's"):
        swapped.run("ops/fadd-x1", np.zeros(64, bool))
    swapped.close()
    assert_still_serves(runner)


def test_clients_without_a_valid_certificate_are_refused(services, runner, tmp_path):
    other = tls.make_certs(tmp_path / "other")  # a CA the servers do not trust
    no_cert = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    no_cert.load_verify_locations(tls.cert_path(services.tls_dir, "ca"))
    foreign = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    foreign.load_verify_locations(tls.cert_path(services.tls_dir, "ca"))
    foreign.load_cert_chain(tls.cert_path(other, "client"), tls.key_path(other, "client"))
    for role, addr in (("garbler", services.garbler_addr),
                       ("evaluator", services.evaluator_addr)):
        before = runner.health(role)["sessions"]["rejected"]
        for ctx in (no_cert, foreign):
            with pytest.raises((ssl.SSLError, ConnectionError, OSError)):
                sock = raw(addr, services.tls_dir, ctx=ctx)
                with contextlib.closing(sock):  # TLS 1.3: refused at the first read
                    hello(sock)
                    assert read_msg(sock) is None
                    raise ConnectionError("closed without serving")
        assert runner.health(role)["sessions"]["rejected"] == before + 2  # and logged
    assert_still_serves(runner)


def test_sigterm_stops_a_daemon_gracefully(services, cache, tmp_path):
    log = tmp_path / "evaluator.log"
    daemon = start_daemon("evaluator", ["--tls-dir", str(services.tls_dir)], log,
                          env={"SNAIL_CACHE_DIR": str(cache)})
    with contextlib.closing(raw(daemon.address, services.tls_dir)) as sock:
        hello(sock)
        assert daemon.stop(timeout=10) == 0
        assert read_msg(sock)["t"] == "bye"
    events = [json.loads(line)["event"] for line in log.read_text().splitlines()]
    assert events[0] == "listening" and events[-1] == "stopped"


def test_a_session_whose_garbler_never_comes_times_out(services, cache, tmp_path):
    circuit, schedule = registry.compiled("ops/fadd-x1")
    daemon = start_daemon("evaluator", ["--tls-dir", str(services.tls_dir),
                                        "--session-timeout", "2", "--max-sessions", "1"],
                          tmp_path / "evaluator.log", env={"SNAIL_CACHE_DIR": str(cache)})
    try:
        with contextlib.closing(raw(daemon.address, services.tls_dir)) as sock:
            hello(sock)
            start = dict(circuit="ops/fadd-x1", hash=circuit.content_hash())
            sock.sendall(encode_bytes(messages.make("session_start", sid=SID, **start)))
            sock.sendall(encode_bytes(messages.make(
                "input_labels", sid=SID, start=0, total=schedule.n_inputs + 2,
                labels=bytes(16 * (schedule.n_inputs + 2)))))
            other = bytes(16)
            sock.sendall(encode_bytes(messages.make("session_start", sid=other, **start)))
            busy = read_msg(sock)
            assert (busy["code"], busy["sid"]) == (errors.BUSY, other)
            expired = read_msg(sock)  # the session timeout's, naming who never came
            assert (expired["code"], expired["sid"]) == (errors.TIMEOUT, SID)
            assert "garbler" in expired["message"]
            sock.sendall(encode_bytes(messages.make("health_request")))
            sessions = read_msg(sock)["sessions"]
            assert (sessions["active"], sessions["failed"]) == (0, 1)
    finally:
        daemon.stop()


def test_circuits_over_the_daemons_and_limit_are_refused(cache):
    with embedded_services(env={"SNAIL_CACHE_DIR": str(cache)},
                           extra_args=("--max-and-gates", "100000")) as small, \
            SecureRunner(small.garbler_addr, small.evaluator_addr, small.tls_dir,
                         timeout=60) as limited:
        n_inputs = registry.interface("loc/lm-sil-ldlt-n4").n_inputs  # 414,471 AND gates
        # the client reads the limit from the servers' capabilities and asks for nothing
        # beyond it (nor builds it)
        with pytest.raises(ServiceError, match=r"more than 100,000.*more than the servers "
                                               r"compile \(their --max-and-gates\)"):
            limited.run("loc/lm-sil-ldlt-n4", np.zeros(n_inputs, bool))
        for role in ("garbler", "evaluator"):
            assert limited.health(role)["sessions"]["failed"] == 0
        # a client that does not look is refused by the servers themselves
        for link in (s.any_link() for s in limited._runner.replicas.values()):
            link.conn.info.pop("max_and_gates")
        with pytest.raises(ServiceError, match=r"too_large.*more than 100,000.*"
                                               r"\(this .*--max-and-gates\)"):
            limited.run("loc/lm-sil-ldlt-n4", np.zeros(n_inputs, bool))
        assert_still_serves(limited)
        # the other server learns of the refusal (or crosses the limit itself) a moment
        # after the client hears of it
        for role in ("garbler", "evaluator"):
            wait_for(lambda r=role: limited.health(r)["sessions"], lambda now: now["active"] == 0)
