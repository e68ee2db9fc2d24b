"""The table link (--table-link tls | aead | digest, snail_common/net/datalink.py): each
mode gives the cleartext circuit's answer and says which it is; a byte changed on the
server link fails the run naming that link (in aead and digest, a localization's record
blames party server-link); a stranger or a replayed token on the data port is dropped and
logged; servers set to different modes refuse, naming the flag."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import re
import socket
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from fault_proxy import FaultProxy
from hypothesis import given, settings
from hypothesis import strategies as st
from shared_paths import EXAMPLES

from snail_client.audit import IntegrityFailure
from snail_client.blocking import SecureRunner
from snail_client.embedded import Daemon, make_certs, start_daemon
from snail_client.links import ServiceError
from snail_client.localize import GarbledBackend, Options, failure_record, localize
from snail_common.circuit import evaluate_bits, registry
from snail_common.loc.problem import load_problem
from snail_common.net import errors, tls
from snail_common.net.conn import connect, new_event_loop, parse_addr
from snail_common.net.datalink import AEAD, PREAMBLE, TOKEN_BYTES, DataPort
from snail_common.net.frames import BodyPool, FrameReader, decode, encode
from snail_common.net.seal import (
    EVALUATOR_TO_GARBLER,
    GARBLER_TO_EVALUATOR,
    SLACK,
    FrameSeal,
)

MODES = ("tls", "aead", "digest")
IDLE_S = 4  # the daemons' --idle-timeout (the garbler's pool closes its idle links at 5 s)
SMALL = "ops/fadd-x1"
LARGE = "ops/fmul-x256"  # ~7 MB of tables: a byte well inside the stream can be changed
FLIP_IN = 3 << 19  # 1.5 MiB into the next run's stream: inside the second frame's tables
# When a byte of the tables changed on the server link, the evaluator fails the session
# and closes the link; both servers then tell the client, and the client reports whichever
# word comes first: the evaluator's (in aead and digest an integrity failure blaming the
# server link), or the garbler's loss of the evaluator (both name the server link). What
# the evaluator found is in its session line, per mode: the outcome and reason, None where
# TLS refuses the record before the evaluator reads it.
SERVER_LINK = "garbler's table stream|garbler .* lost the evaluator|changed on the server link"
PROBLEM = EXAMPLES / "synthetic_n6.json"  # 5.7 MB of tables a run: FLIP_IN is inside them
FOUND = {"tls": None,
         "aead": ("link", "frame .* fails its seal: changed on the wire"),
         "digest": ("digest", "not the ones the garbler signed .* the garbler or the server "
                              "link")}


# ---- the seal -------------------------------------------------------------------------
def sealed_pair() -> tuple[FrameSeal, FrameSeal]:
    key = os.urandom(32)
    return (FrameSeal(key, GARBLER_TO_EVALUATOR, EVALUATOR_TO_GARBLER),
            FrameSeal(key, EVALUATOR_TO_GARBLER, GARBLER_TO_EVALUATOR))


def tables(n: int, sid: bytes = bytes(16)) -> dict:
    return {"t": "tables", "sid": sid, "data": os.urandom(n)}


def opened(receiver: FrameSeal, frame: list) -> bytes:
    body = b"".join(bytes(p) for p in frame[1:])
    out = bytearray(len(body) + SLACK)
    return bytes(out[: receiver.open(memoryview(body), memoryview(out))])


def test_a_sealed_frame_opens_to_its_body_and_hides_it():
    garbler, evaluator = sealed_pair()
    msg = tables(100_000)
    frame = garbler.seal(encode(msg))
    plain = b"".join(bytes(p) for p in encode(msg)[1:])
    assert msg["data"] not in b"".join(bytes(p) for p in frame)
    assert opened(evaluator, frame) == plain


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 20_000 + 40))
def test_any_changed_byte_fails_the_seal(at):
    garbler, evaluator = sealed_pair()
    frame = garbler.seal(encode(tables(20_000)))
    body = bytearray(b"".join(bytes(p) for p in frame[1:]))
    body[at % len(body)] ^= 0x80
    with pytest.raises(errors.ProtocolError) as err:
        opened(evaluator, [frame[0], bytes(body)])
    assert err.value.code == errors.LINK


def test_a_replayed_reordered_or_reflected_frame_fails_the_seal():
    garbler, evaluator = sealed_pair()
    first, second = (garbler.seal(encode(tables(1000))) for _ in range(2))
    opened(evaluator, first)
    with pytest.raises(errors.ProtocolError):  # the first again, in the second's place
        opened(evaluator, first)
    garbler, evaluator = sealed_pair()
    first, second = (garbler.seal(encode(tables(1000))) for _ in range(2))
    with pytest.raises(errors.ProtocolError):  # out of order
        opened(evaluator, second)
    garbler, _ = sealed_pair()
    with pytest.raises(errors.ProtocolError):  # sent back to its sender
        opened(garbler, garbler.seal(encode(tables(1000))))


@settings(max_examples=20, deadline=None)
@given(st.lists(st.integers(1, 300_000), min_size=1, max_size=12))
def test_a_sealed_stream_read_in_any_pieces_gives_its_frames(cuts):
    garbler, evaluator = sealed_pair()
    sent = [tables(n) for n in (1_200_000, 50, 300_000)] + [{"t": "done", "sid": bytes(16)}]
    wire = b"".join(bytes(p) for m in sent for p in garbler.seal(encode(m)))
    reader = FrameReader(seal=evaluator)
    got, at, i = [], 0, 0
    while at < len(wire):
        buf = reader.buffer()
        n = min(len(buf), cuts[i % len(cuts)], len(wire) - at)
        buf[:n] = wire[at : at + n]
        got += [m for m, _ in reader.filled(n)]
        at, i = at + n, i + 1
    assert [m["t"] for m in got] == [m["t"] for m in sent]
    for m, want in zip(got[:3], sent[:3]):
        assert bytes(m["data"]) == want["data"]
    assert isinstance(got[0]["data"], memoryview)  # the big frame's data is lent, not copied


# ---- real daemons ---------------------------------------------------------------------
@dataclass
class Pair:
    """An evaluator and a garbler in one mode, the garbler's link through a proxy."""

    mode: str
    root: Path
    tls_dir: Path
    evaluator: Daemon
    garbler: Daemon
    proxy: FaultProxy

    def client(self, **kw: object) -> SecureRunner:
        return SecureRunner(self.garbler.address, self.evaluator.address, self.tls_dir,
                            timeout=120, **kw)

    def lines(self, role: str, kind: str) -> list[dict]:
        log = getattr(self, role).log
        return [e for e in map(json.loads, log.read_text().splitlines())
                if e.get("event") == kind]


@contextlib.contextmanager
def pair_of(root: Path, evaluator_mode: str, garbler_mode: str) -> Iterator[Pair]:
    tls_dir = make_certs(root / "tls")
    env = {"SNAIL_CACHE_DIR": os.environ["SNAIL_CACHE_DIR"]}
    flags = ["--tls-dir", str(tls_dir), "--log-level", "info", "--session-timeout", "10",
             "--handshake-timeout", "3", "--idle-timeout", str(IDLE_S)]
    evaluator = start_daemon("evaluator", [*flags, "--table-link", evaluator_mode],
                             root / "evaluator.log", env=env)
    try:
        with FaultProxy(parse_addr(evaluator.address)) as proxy:
            garbler = start_daemon("garbler", [*flags, "--table-link", garbler_mode,
                                               "--evaluator", proxy.address],
                                   root / "garbler.log", env=env)
            try:
                yield Pair(evaluator_mode, root, tls_dir, evaluator, garbler, proxy)
            finally:
                garbler.stop()
    finally:
        evaluator.stop()


@pytest.fixture(scope="module", params=MODES)
def pair(request, tmp_path_factory):
    registry.compiled(LARGE)  # on disk before the daemons need it
    with pair_of(tmp_path_factory.mktemp(request.param), request.param,
                 request.param) as p:
        yield p


def cleartext(circuit_id: str, bits: np.ndarray) -> np.ndarray:
    _, schedule = registry.compiled(circuit_id)
    return evaluate_bits(schedule, bits[None])[0]


def random_bits(circuit_id: str, seed: int = 0) -> np.ndarray:
    _, schedule = registry.compiled(circuit_id)
    return np.random.default_rng(seed).random(schedule.n_inputs) < 0.5


def test_each_mode_gives_the_cleartext_answer_and_says_which_it_is(pair):
    with pair.client() as client:
        for circuit_id in (SMALL, LARGE):
            bits = random_bits(circuit_id)
            np.testing.assert_array_equal(client.run(circuit_id, bits),
                                          cleartext(circuit_id, bits))
        for role in ("garbler", "evaluator"):
            assert client.health(role)["table_link"] == pair.mode
    for role in ("garbler", "evaluator"):
        sessions = pair.lines(role, "session")
        assert len(sessions) >= 2 and {s["table_link"] for s in sessions} == {pair.mode}
        assert pair.lines(role, "listening")[0]["table_link"] == pair.mode
    links = pair.lines("evaluator", "data_link_open")
    assert (len(links) >= 1) == (pair.mode != "tls")


def test_a_byte_changed_on_the_server_link_fails_the_run_naming_it(pair):
    bits = random_bits(LARGE, 1)
    before = len(pair.lines("evaluator", "session"))
    pair.proxy.flip_in = FLIP_IN
    try:
        with pair.client() as client, pytest.raises(ServiceError, match=SERVER_LINK):
            client.run(LARGE, bits)
    finally:
        pair.proxy.flip_in = None
    if FOUND[pair.mode] is not None:
        outcome, reason = FOUND[pair.mode]
        deadline = time.monotonic() + 60  # hang guard: the line follows the client's error
        while not (failed := [s for s in pair.lines("evaluator", "session")[before:]
                              if s["outcome"] != "ok"]):
            assert time.monotonic() < deadline, "no failed session line"
            time.sleep(0.05)
        assert [s["outcome"] for s in failed] == [outcome]
        assert re.search(reason, failed[0]["reason"]), failed[0]["reason"]
    with pair.client() as client:  # the next run is served on a new link
        np.testing.assert_array_equal(client.run(LARGE, bits), cleartext(LARGE, bits))


@pytest.mark.parametrize("mode", ["aead", "digest"])  # tls: TLS refuses the record first
def test_a_localization_whose_tables_changed_on_the_server_link_blames_the_link(tmp_path,
                                                                                mode):
    """The evaluator cannot tell a garbler that sends wrong bytes from a link that changes
    them: the record's error names neither server but the link between them. The garbler
    here does not hear the evaluator close its link (``hold_closes``), so the evaluator's
    word is the one that reaches the client, whatever the machine's speed; every run is
    garbled when it is invoked (``ahead=0``), so the run whose tables change is one the
    client waits on. The garbler does hear the evaluator's last word on the link (the
    error it closes the link with), and passes on its code. A pair of its own: the held
    closes are every link's of the proxy."""
    options = Options()
    with pair_of(tmp_path, mode, mode) as pair:
        pair.proxy.flip_in, pair.proxy.hold_closes = FLIP_IN, True
        try:
            with pair.client(ahead=0) as runner, pytest.raises(IntegrityFailure) as info:
                localize(load_problem(PROBLEM), options, GarbledBackend(runner))
        finally:
            pair.proxy.flip_in = None
            pair.proxy.release()
        with pair.client() as client:  # no server refused: the next run is served
            np.testing.assert_array_equal(client.run(SMALL, random_bits(SMALL)),
                                          cleartext(SMALL, random_bits(SMALL)))
    record = json.loads(json.dumps(failure_record(info.value, options)))
    assert record["status"] == "failed" and "rvec" not in record
    error = record["error"]
    assert (error["kind"], error["party"], error["run"]) == ("integrity", "server-link", 0)
    assert "changed on the server link" in error["detail"]
    assert "cannot tell a garbler that sends wrong bytes from a link that changes them" \
        in error["detail"]
    assert re.search(FOUND[mode][1], error["detail"]), error["detail"]
    assert record["audits"] == {"runs": 1, "audited": 0, "failed": 1}


def closed_by_peer(sock: socket.socket) -> bytes:
    """What the server sent before it closed (or reset) the connection (a minute's hang
    guard: a server that keeps it open fails the test with a timeout)."""
    sock.settimeout(60)
    got = b""
    with contextlib.suppress(ConnectionResetError):
        while chunk := sock.recv(65536):
            got += chunk
    return got


def refusals(pair: Pair, before: int, count: int = 1) -> list[dict]:
    """The evaluator's ``data_link_refused`` lines after the first ``before``, once there
    are ``count`` of them (they follow the close: polled, a minute's hang guard)."""
    deadline = time.monotonic() + 60
    while len(lines := pair.lines("evaluator", "data_link_refused")) < before + count:
        assert time.monotonic() < deadline, "no data_link_refused line"
        time.sleep(0.05)
    return lines[before:]


def test_a_stranger_on_the_port_is_dropped_and_logged(pair):
    if pair.mode == "tls":
        pytest.skip("in tls mode the port speaks TLS only (test_service_e2e's rejections)")
    before = len(pair.lines("evaluator", "data_link_refused"))
    with socket.create_connection(parse_addr(pair.evaluator.address)) as sock:
        sock.sendall(PREAMBLE + os.urandom(32) + b"more bytes a stranger sends")
        assert closed_by_peer(sock) == b""
    assert "no valid token" in refusals(pair, before)[0]["reason"]
    with pair.client() as client:
        np.testing.assert_array_equal(client.run(SMALL, random_bits(SMALL)),
                                      cleartext(SMALL, random_bits(SMALL)))


def read_frame(sock: socket.socket) -> bytes:
    """One frame's body (a minute's hang guard)."""
    sock.settimeout(60)
    head = sock.recv(4, socket.MSG_WAITALL)
    return sock.recv(int.from_bytes(head, "big"), socket.MSG_WAITALL)


@contextlib.contextmanager
def data_link(pair: Pair) -> Iterator[tuple[socket.socket, dict]]:
    """A data link opened by hand (this test presents the garbler's certificate over
    TLS, as the garbler does): its socket, once the evaluator's capabilities came back
    on it, and what the TLS connection's capabilities granted."""
    host, port = parse_addr(pair.evaluator.address)
    loop = new_event_loop()
    try:
        control = loop.run_until_complete(connect(
            host, port, tls.client_context(pair.tls_dir, "garbler"), "garbler", "evaluator",
            server_name=host))
        with socket.create_connection((host, port)) as sock:
            sock.sendall(PREAMBLE + control.info["link_token"])
            body = read_frame(sock)
            if pair.mode == "aead":
                seal = FrameSeal(control.info["link_key"], GARBLER_TO_EVALUATOR,
                                 EVALUATOR_TO_GARBLER)
                out = bytearray(len(body) + SLACK)
                body = bytes(out[: seal.open(memoryview(body), memoryview(out))])
            assert decode(body)["t"] == "capabilities"
            yield sock, control.info
        control.abort()
    finally:
        loop.close()


def test_a_token_is_good_once(pair):
    if pair.mode == "tls":
        pytest.skip("tls mode hands out no token")
    address = parse_addr(pair.evaluator.address)
    before = len(pair.lines("evaluator", "data_link_refused"))
    with data_link(pair) as (_, granted), socket.create_connection(address) as again:
        again.sendall(PREAMBLE + granted["link_token"])  # a replay: dropped
        assert closed_by_peer(again) == b""
    assert "no valid token" in refusals(pair, before)[0]["reason"]


def test_an_idle_data_link_is_closed_after_the_idle_timeout(pair):
    """Its TLS connection is busy while the link lives; the link itself idles out (and
    takes the TLS connection with it)."""
    if pair.mode == "tls":
        pytest.skip("tls mode has no data link")
    with data_link(pair) as (sock, _):
        t0 = time.monotonic()
        closed_by_peer(sock)  # the evaluator's timeout error, then the close
        assert time.monotonic() - t0 >= IDLE_S * 0.9


def test_a_connection_that_sends_nothing_is_closed_after_the_handshake_timeout(pair):
    if pair.mode == "tls":
        pytest.skip("tls mode: the TLS handshake timeout (asyncio's own)")
    with socket.create_connection(parse_addr(pair.evaluator.address)) as sock:
        t0 = time.monotonic()
        assert closed_by_peer(sock) == b""
        assert time.monotonic() - t0 >= 3 * 0.9  # never before --handshake-timeout
    assert any("nothing sent within 3 s" in e["reason"]
               for e in pair.lines("evaluator", "connection_rejected"))


def test_a_stranger_that_goes_silent_is_dropped_at_its_first_wrong_byte(tmp_path):
    """Not held for --handshake-timeout (300 s here) waiting for an opening its first
    bytes already rule out: wrong from the first byte, or from the ninth."""
    tls_dir = make_certs(tmp_path / "tls")
    evaluator = start_daemon("evaluator", [
        "--tls-dir", str(tls_dir), "--log-level", "info", "--handshake-timeout", "300",
        "--table-link", "aead"], tmp_path / "evaluator.log",
        env={"SNAIL_CACHE_DIR": os.environ["SNAIL_CACHE_DIR"]})
    openings = (b"GET / HTTP/1.1\r\n", PREAMBLE[:8] + b"X")
    try:
        for opening in openings:
            with socket.create_connection(parse_addr(evaluator.address)) as sock:
                sock.sendall(opening)  # and then nothing more
                assert closed_by_peer(sock) == b""  # a minute's guard, not a timing
        deadline = time.monotonic() + 60  # hang guard: the lines follow the closes
        while len(refused := [e for e in map(json.loads, evaluator.log.read_text()
                                              .splitlines())
                              if e.get("event") == "data_link_refused"]) < len(openings):
            assert time.monotonic() < deadline, "no data_link_refused line"
            time.sleep(0.05)
    finally:
        evaluator.stop()
    assert [e["reason"] for e in refused] == \
        ["its first bytes are not the data link's preamble"] * len(openings)


def test_an_opening_in_pieces_is_admitted_and_a_wrong_byte_refused_at_once():
    """The gate (datalink.py) byte by byte: every prefix of the preamble waits for more,
    the first byte off it is refused there, whatever came before."""

    class Transport:
        def __init__(self) -> None:
            self.aborted = False

        def get_extra_info(self, name: str) -> object:
            return ("127.0.0.1", 1) if name == "peername" else None

        def abort(self) -> None:
            self.aborted = True

    async def feed(data: bytes) -> tuple[list[int], list[bytes]]:
        """The bytes after which the gate refused, and the openings it passed on."""
        refusals: list[int] = []
        port = DataPort(AEAD, 300, logging.getLogger("test"), lambda conn: None,
                        lambda: refusals.append(len(fed)), 10, BodyPool(0))
        admitted: list[bytes] = []
        port.admit = lambda transport, opening: admitted.append(opening)
        gate, transport, fed = port.gate(), Transport(), bytearray()
        gate.connection_made(transport)
        for byte in data:
            if transport.aborted:
                break
            gate.get_buffer(1)[0] = byte
            fed.append(byte)
            gate.buffer_updated(1)
        gate.connection_lost(None)
        return refusals, admitted

    token = os.urandom(TOKEN_BYTES)
    assert asyncio.run(feed(PREAMBLE + token)) == ([], [PREAMBLE + token])
    for at in (0, 5, len(PREAMBLE) - 1):
        wrong = PREAMBLE[:at] + bytes([PREAMBLE[at] ^ 1]) + PREAMBLE[at + 1:] + token
        assert asyncio.run(feed(wrong)) == ([at + 1], [])


@pytest.mark.parametrize("evaluator_mode, garbler_mode", [("aead", "tls"), ("tls", "digest")])
def test_servers_in_different_modes_refuse_naming_the_flag(tmp_path, evaluator_mode,
                                                           garbler_mode):
    with pair_of(tmp_path, evaluator_mode, garbler_mode) as p, p.client() as client, \
            pytest.raises(ServiceError, match="--table-link must be the same on both"):
        client.run(SMALL, random_bits(SMALL))


def test_the_data_link_and_its_tls_connection_end_together():
    """Either end of a tied pair ends the other (a data link is no use alone)."""
    from snail_common.net.conn import Connection

    async def scenario() -> list[bool]:
        a, b, c = Connection(), Connection(), Connection()
        a.tie(b)
        assert a.tied_open and b.tied_open
        b.abort()
        c.abort()
        return [a.ended, b.ended, c.ended, a.tied_open]

    assert asyncio.run(scenario()) == [True, True, True, False]
