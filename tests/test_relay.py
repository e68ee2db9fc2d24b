"""The relay: a device reaches its map owner only through the evaluator (``--relay``),
over TLS end to end with the map owner, so the map owner sees the evaluator's address and
never the device's; four processes on loopback (this test is the device).

- A relayed frame's pose equals, bit for bit, the direct path's and the cleartext
  circuit's; so do a relayed track's (the command line) and the bench says relay true.
- The map owner never saw the device: every device connection it logged, while they are
  open, is a socket of the evaluator's process (/proc/net/tcp and /proc/PID/fd), and on
  the direct path the same check finds this process's: the check can tell them apart.
- The evaluator carries ciphertext only: no relay_data payload holds a message name of
  the map-owner protocol, and the device's first payload is a TLS handshake record.
- A map owner the evaluator's operator did not allow is refused ``forbidden`` (naming the
  field and the flag) with no connection made; a map owner that is down, or goes away,
  fails the link with an error naming it, and the evaluator serves on.
"""

from __future__ import annotations

import ast
import contextlib
import json
import os
import socket
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from test_garbler_map_owners import Listener
from test_mapowner_e2e import OPTIONS, frame_files, scene, write_map
from test_service_e2e import hello, raw, read_msg

from snail_bench.cli import main as bench
from snail_client.blocking import SecureRunner
from snail_client.cli import main as client
from snail_client.embedded import Services, embedded_services, start_daemon
from snail_client.links import ServiceError
from snail_client.localize import GarbledBackend
from snail_client.mapowner import MapOwnerLink
from snail_common.loc import owner
from snail_common.loc.backends import CircuitBackend
from snail_common.net import conn as conn_module
from snail_common.net import errors, frames, messages
from snail_common.net.frames import encode_bytes
from snail_common.net.messages import RELAY_DATA

M = 64  # map points
INNER = (b"map_info_request", b"map_info", b"ot_base_a", b"ot_ext_u", b"sel_table",
         b"pad_correction_request", b"pad_correction")  # the inner protocol's names
ESTABLISHED = "01"  # a TCP state in /proc/net/tcp


def lines(log: Path, kind: str) -> list[dict]:
    return [e for e in map(json.loads, log.read_text().splitlines())
            if e.get("event") == kind]


def _hex_address(text: str) -> tuple[str, int]:
    """An IPv4 ``0100007F:1F90`` of /proc/net/tcp as (ip, port)."""
    ip, port = text.split(":")
    return socket.inet_ntoa(bytes.fromhex(ip)[::-1]), int(port, 16)


def established_inodes() -> dict[tuple[tuple[str, int], tuple[str, int]], int]:
    """(local, remote) -> socket inode of every established IPv4 TCP socket here."""
    found = {}
    for row in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        cols = row.split()
        if cols[3] == ESTABLISHED:
            found[_hex_address(cols[1]), _hex_address(cols[2])] = int(cols[9])
    return found


def holder(inode: int, pids: dict[str, int]) -> str | None:
    """Which of ``pids`` (name -> pid) holds the socket ``inode`` open."""
    target = f"socket:[{inode}]"
    for name, pid in pids.items():
        for fd in Path(f"/proc/{pid}/fd").iterdir():
            with contextlib.suppress(OSError):
                if os.readlink(fd) == target:
                    return name
    return None


def device_connections(services: Services) -> list[str]:
    """Whose process holds each device (role client) connection the map owner logged and
    still has open: the map owner's view of where its devices are, tied to processes."""
    mapd = services.map_owners[0]
    where = ("127.0.0.1", int(mapd.address.rsplit(":", 1)[1]))
    opened: dict[str, dict] = {}
    for entry in map(json.loads, mapd.log.read_text().splitlines()):
        if entry.get("peer_role") != "client":
            continue
        if entry["event"] == "connection_open":
            opened[entry["address"]] = entry
        elif entry["event"] == "connection_closed":
            opened.pop(entry["address"], None)
    sockets = established_inodes()
    pids = {"evaluator": services.evaluator.process.pid,
            "garbler": services.garbler.process.pid, "device": os.getpid()}
    owners = []
    for address in opened:
        peer = tuple(ast.literal_eval(address))  # the peer's (ip, port) as logged
        inode = sockets.get((peer, where))  # that peer's own end of the connection
        if inode is not None:  # else closed since (its close not logged yet)
            owners.append(holder(inode, pids) or "another process")
    return owners


@dataclass
class Run:
    """One frame localized against the module's map owner, and what was seen meanwhile."""

    pose: tuple[np.ndarray, np.ndarray, float]
    holders: list[str]  # whose process each device connection of the map owner is
    link_bytes: int = 0  # the device's bytes on its map-owner links (both ways)
    relayed: dict[str, list[bytes]] = field(default_factory=dict)  # relay_data payloads


@pytest.fixture(scope="module")
def services(tmp_path_factory):
    root = tmp_path_factory.mktemp("relay")
    points, _, _ = scene(M)
    with embedded_services(log_level="info", maps=(write_map(points, root / "map.json"),)
                           ) as svc:
        yield svc


def localize(services: Services, relay: str | None) -> Run:
    """The synthetic n = 6 frame, its map points selected from the module's map owner and
    its runs padded to OPTIONS' count; the map owner's device connections are tied to
    processes while the links are still open."""
    _, frame, _ = scene(M)
    mapd = services.map_owners[0].address
    with MapOwnerLink(mapd, services.tls_dir, relay=relay) as link, SecureRunner(
            services.garbler_addr, services.evaluator_addr, services.tls_dir) as runner:
        published = link.open()
        handle, masked = link.select(frame.map_ids)
        runner.use_frame(handle, mapd, relay)
        got = owner.localize_shared(frame, published, masked, OPTIONS,
                                    GarbledBackend(runner))
        holders = device_connections(services)
        corrections = runner.async_runner.totals
        device_owner = sum(link.traffic.values()) + sum(
            corrections.get(k, 0) for k in ("client_to_mapowner", "mapowner_to_client"))
    return Run((got.rvec, got.tvec, got.cost), holders, device_owner)


@pytest.fixture(scope="module")
def runs(services):
    """The frame through the relay (every relay_data frame this device sent or received
    recorded) and directly."""
    relayed: dict[str, list[bytes]] = {"up": [], "down": []}
    encode, decode = conn_module.encode, frames.decode

    def sent(msg, *args):
        if msg.get("t") == "relay_data":
            relayed["up"].append(bytes(msg["data"]))
        return encode(msg, *args)

    def received(body, lend=False):
        msg = decode(body, lend)
        if msg.get("t") == "relay_data":
            relayed["down"].append(bytes(msg["data"]))
        return msg

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(conn_module, "encode", sent)
        mp.setattr(frames, "decode", received)
        through = localize(services, services.evaluator_addr)
    through.relayed = relayed
    return {"relay": through, "direct": localize(services, None)}


def test_a_relayed_frame_is_the_direct_one_and_the_cleartext_circuit_bit_for_bit(runs):
    points, frame, _ = scene(M)
    published, values = owner.owner_values(points)
    clear = owner.localize_known(frame, published, values, OPTIONS, CircuitBackend())
    for run in runs.values():
        rvec, tvec, cost = run.pose
        assert np.array_equal(rvec, clear.rvec) and np.array_equal(tvec, clear.tvec)
        assert cost == clear.cost


def test_the_map_owner_sees_the_evaluator_never_the_device(runs, services):
    # the selection link and the pad corrections' link, both the evaluator's sockets
    assert len(runs["relay"].holders) >= 2
    assert set(runs["relay"].holders) == {"evaluator"}
    # the control: the same check on the direct path finds this process, the device
    assert len(runs["direct"].holders) >= 2 and set(runs["direct"].holders) == {"device"}
    relays = [r for r in lines(services.evaluator.log, "relay") if r["outcome"] == "ok"]
    assert len(relays) >= 2
    mapd = services.map_owners[0].address
    assert {r["map_owner"] for r in relays} == {mapd}
    assert all(r["bytes_to_owner"] > 0 and r["bytes_to_device"] > 0 for r in relays)


def test_the_evaluator_carries_only_ciphertext(runs):
    relayed = runs["relay"].relayed
    up, down = relayed["up"], relayed["down"]
    assert up and down and max(map(len, up + down)) <= RELAY_DATA
    # every byte of the device's map-owner links went through the relay, inside TLS
    assert sum(map(len, up + down)) > runs["relay"].link_bytes
    assert up[0][:2] == b"\x16\x03"  # a TLS handshake record (the ClientHello)
    plain = encode_bytes(messages.make("map_info_request"))
    assert b"map_info_request" in plain  # what a plaintext frame would show
    for name in INNER:
        assert not any(name in payload for payload in up + down), name
    assert not any(name in b"".join(up) or name in b"".join(down) for name in INNER)


def relay_refusal(evaluator: str, tls_dir: Path, target: Listener) -> dict:
    """The evaluator's answer to a relay_open naming ``target``; the connection must be
    closed after it."""
    with contextlib.closing(raw(evaluator, tls_dir)) as sock:
        hello(sock)
        sock.sendall(encode_bytes(messages.make(
            "relay_open", map_owner=f"127.0.0.1:{target.port}")))
        reply = read_msg(sock)
        assert read_msg(sock) is None  # and the connection is closed
    return reply


def test_a_relay_to_a_map_owner_the_operator_did_not_allow_is_forbidden(services):
    before = len(lines(services.evaluator.log, "relay"))
    target = Listener()
    try:
        reply = relay_refusal(services.evaluator_addr, services.tls_dir, target)
        assert reply["t"] == "error" and reply["code"] == errors.FORBIDDEN
        assert "'map_owner'" in reply["message"] and "--map-owner" in reply["message"]
        link = MapOwnerLink(f"127.0.0.1:{target.port}", services.tls_dir,
                            relay=services.evaluator_addr)
        with link, pytest.raises(ServiceError, match=r"forbidden: the relay at \S+: field "
                                                     r"'map_owner'.*--map-owner"):
            link.open()
        assert target.dialled() == 0
    finally:
        target.close()
    refused = lines(services.evaluator.log, "relay")[before:]
    assert {r["outcome"] for r in refused} == {errors.FORBIDDEN}
    assert len(refused) == 2 and all(r["bytes_to_owner"] == 0 for r in refused)


def test_a_relay_takes_a_connection_of_its_own_and_nothing_else(services):
    mapd = services.map_owners[0].address
    with contextlib.closing(raw(services.evaluator_addr, services.tls_dir)) as sock:
        hello(sock)
        sock.sendall(encode_bytes(messages.make("health_request")))
        assert read_msg(sock)["t"] == "health"
        sock.sendall(encode_bytes(messages.make("relay_open", map_owner=mapd)))
        reply = read_msg(sock)
        assert reply["code"] == errors.UNEXPECTED and "first message" in reply["message"]
    with contextlib.closing(raw(services.evaluator_addr, services.tls_dir)) as sock:
        hello(sock)
        sock.sendall(encode_bytes(messages.make("relay_data", data=b"\x16\x03")))
        reply = read_msg(sock)
        assert reply["code"] == errors.UNEXPECTED and "relay_data" in reply["message"]
    with contextlib.closing(raw(services.evaluator_addr, services.tls_dir)) as sock:
        hello(sock)
        sock.sendall(encode_bytes(messages.make("relay_open", map_owner=mapd)))
        assert read_msg(sock)["t"] == "relay_ready"
        sock.sendall(encode_bytes(messages.make("health_request")))
        reply = read_msg(sock)
        assert reply["code"] == errors.UNEXPECTED and "relay_data only" in reply["message"]


@pytest.fixture
def lone_evaluator(tmp_path, services):
    """An evaluator of its own that may relay to a live map owner (its own too) and to
    an address where nothing listens."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        down = f"127.0.0.1:{sock.getsockname()[1]}"  # closed at once: nothing listens
    points, _, _ = scene(M)
    mapd = start_daemon("mapd", ["--map", str(write_map(points, tmp_path / "map.json")),
                                 "--tls-dir", str(services.tls_dir)], tmp_path / "mapd.log")
    evaluator = start_daemon("evaluator", ["--tls-dir", str(services.tls_dir),
                                           "--map-owner", down, "--map-owner", mapd.address,
                                           "--log-level", "info"], tmp_path / "evaluator.log")
    try:
        yield evaluator, mapd, down
    finally:
        evaluator.stop()
        mapd.stop()


def test_a_map_owner_down_or_gone_fails_by_name_and_the_evaluator_serves_on(
        lone_evaluator, services):
    evaluator, mapd, down = lone_evaluator
    tls_dir = services.tls_dir
    with MapOwnerLink(down, tls_dir, relay=evaluator.address) as link, pytest.raises(
            ServiceError, match=rf"cannot reach the map owner at {down}"):
        link.open()
    _, frame, _ = scene(M)
    with MapOwnerLink(mapd.address, tls_dir, relay=evaluator.address) as link:
        link.open()  # the evaluator served on
        link.select(frame.map_ids)
        mapd.stop()
        with pytest.raises(ServiceError, match=rf"map owner at {mapd.address}"):
            link.select(frame.map_ids)
    with contextlib.closing(raw(evaluator.address, tls_dir)) as sock:
        hello(sock)
        sock.sendall(encode_bytes(messages.make("health_request")))
        assert read_msg(sock)["t"] == "health"
    outcomes = [(r["map_owner"], r["outcome"]) for r in lines(evaluator.log, "relay")]
    assert outcomes[0] == (down, errors.PEER_LOST)
    assert outcomes[1][0] == mapd.address and len(outcomes) == 2
    assert not lines(evaluator.log, "connection_error")  # no bug surfaced


def test_no_map_owner_allowed_refuses_every_relay(tmp_path, services):
    target = Listener()
    bare = start_daemon("evaluator", ["--tls-dir", str(services.tls_dir)],
                        tmp_path / "bare.log")
    try:
        reply = relay_refusal(bare.address, services.tls_dir, target)
        assert reply["code"] == errors.FORBIDDEN
        assert "relays to no map owner" in reply["message"]
        assert "--map-owner on the evaluator" in reply["message"]
        assert target.dialled() == 0
    finally:
        bare.stop()
        target.close()


def _sequence(tmp_path: Path) -> tuple[Path, Path]:
    """Three snail-frame/1 of the synthetic frame (a still camera) and its map."""
    frame, map_path = frame_files(tmp_path, M)
    one = json.loads(frame.read_text())
    seq = tmp_path / "seq.json"
    seq.write_text(json.dumps([one] * 3))
    return seq, map_path


def test_a_relayed_track_on_the_command_line_is_the_cleartext_circuit(tmp_path):
    """(One frame in flight: by default the depth follows the first frame's round trip,
    and a frame starts from the pose of the frame that many before it.)"""
    seq, map_path = _sequence(tmp_path)
    args = ["track", "--input", str(seq), "--map", str(map_path), "--json",
            "--min-invocations", "3", "--runs-per-frame", "1", "--in-flight", "1"]
    relayed = CliRunner().invoke(client, [*args, "--relay"])
    assert relayed.exit_code == 0, relayed.output
    clear = CliRunner().invoke(client, [*args, "--backend", "cleartext"])
    assert clear.exit_code == 0, clear.output
    g = [json.loads(x) for x in relayed.stdout.splitlines()][:-1]  # then the summary
    c = [json.loads(x) for x in clear.stdout.splitlines()][:-1]
    assert len(g) == 3 and all(r["setting"] == "map-owner" for r in g)
    assert [(r["rvec"], r["tvec"]) for r in g] == [(r["rvec"], r["tvec"]) for r in c]
    assert all(r["traffic"]["mapowner_to_client"] > 0 for r in g[:1])


@pytest.mark.parametrize("args, words", [
    (["--relay"], "--relay: with --map-owner or --map"),
    (["--relay", "--map", "MAP", "--backend", "cleartext"], "only --backend garbled"),
    (["--relay", "nowhere", "--map", "MAP"], "--relay: address 'nowhere'"),
])
def test_relay_flags_that_lead_nowhere_are_exit_2(tmp_path, args, words):
    frame, map_path = frame_files(tmp_path, M)
    args = [str(map_path) if a == "MAP" else a for a in args]
    out = CliRunner().invoke(client, ["localize", "--input", str(frame), *args])
    assert out.exit_code == 2 and words in out.output, out.output


def test_the_bench_track_entry_says_relay(tmp_path):
    out = CliRunner().invoke(bench, ["track", "--map-points", "300", "--frames", "2",
                                     "--relay", "--json"])
    assert out.exit_code == 0, out.output
    (entry,) = json.loads(out.stdout)["track"].values()
    assert entry["setting"] == "map-owner" and entry["relay"] is True
    assert entry["ot"]["used"] > 0
    out = CliRunner().invoke(bench, ["track", "--relay", "--frames", "2"])
    assert out.exit_code == 2 and "--relay: with --map-points" in out.output
