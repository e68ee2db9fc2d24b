"""snail-mapd as an operator meets it: a bad map or certificate is one line and exit 2
naming the field or file; bad frames and misplaced messages from any peer are named
errors, and the daemon serves on."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_garbler_map_owners import Listener
from test_service_e2e import BAD_FRAMES, hello, raw, read_msg

from snail_client.embedded import start_daemon
from snail_client.mapowner import MapOwnerLink
from snail_common.net import errors, messages
from snail_common.net.frames import encode_bytes
from snail_common.net.tls import make_certs

SID = bytes(range(16))
MAP = {"format": "snail-map/1",
       "points": [{"id": 10 + i, "xyz": [float(i), float(i * i % 7), 1.0 + i % 3]}
                  for i in range(20)]}


def mapd(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "snail_mapd", *args], capture_output=True,
                          text=True, timeout=60)


@pytest.fixture(scope="module")
def tls_dir(tmp_path_factory):
    return make_certs(tmp_path_factory.mktemp("tls"))


@pytest.fixture(scope="module")
def daemon(tmp_path_factory, tls_dir):
    root = tmp_path_factory.mktemp("mapd")
    (root / "map.json").write_text(json.dumps(MAP))
    running = start_daemon("mapd", ["--map", str(root / "map.json"), "--tls-dir",
                                    str(tls_dir), "--log-level", "info"], root / "mapd.log")
    yield running
    running.stop()


def test_help_and_version():
    out = mapd("--help")
    assert out.returncode == 0
    for flag in ("--listen", "--map", "--tls-dir", "--max-frames"):
        assert flag in out.stdout
    assert "snail-map/1" in out.stdout and "oblivious" in out.stdout
    out = mapd("--version")
    assert out.returncode == 0 and "version 0.1.0" in out.stdout


@pytest.mark.parametrize("content, field", [
    ({**MAP, "format": "snail-problem/1"}, "format"),
    ({"format": "snail-map/1"}, "points"),
    ({**MAP, "points": MAP["points"] + [{"id": 10, "xyz": [0, 0, 0]}]}, "points[20].id"),
    ({**MAP, "points": [*MAP["points"][:3], {"id": 3, "xyz": [0, "x", 0]}]},
     "points[3].xyz"),
    ({**MAP, "points": [{"id": 1, "xyz": [1, 1, 1]}, {"id": 2, "xyz": [1, 1, 1]}]},
     "coincide"),
    ("{not json", "map.json"),
])
def test_a_bad_map_is_exit_2_naming_the_field(tmp_path, tls_dir, content, field):
    path = tmp_path / "map.json"
    path.write_text(content if isinstance(content, str) else json.dumps(content))
    out = mapd("--listen", "127.0.0.1:0", "--map", str(path), "--tls-dir", str(tls_dir))
    assert out.returncode == 2, out.stderr
    assert out.stderr.count("\n") == 1 and field in out.stderr and "--map" in out.stderr
    assert "Traceback" not in out.stderr


def test_a_missing_map_and_a_corrupt_certificate_are_named(tmp_path):
    make_certs(tmp_path)
    out = mapd("--listen", "127.0.0.1:0", "--map", str(tmp_path / "none.json"),
               "--tls-dir", str(tmp_path))
    assert out.returncode == 2 and "none.json" in out.stderr
    (tmp_path / "map.json").write_text(json.dumps(MAP))
    (tmp_path / "mapowner.pem").write_text("not a certificate\n")
    out = mapd("--listen", "127.0.0.1:0", "--map", str(tmp_path / "map.json"),
               "--tls-dir", str(tmp_path))
    assert out.returncode == 2
    assert out.stderr.count("\n") == 1 and "mapowner.pem" in out.stderr


def assert_serves(daemon, tls_dir) -> None:
    """A device still gets the published map and a selection."""
    with MapOwnerLink(daemon.address, tls_dir) as link:
        assert list(link.open().ids) == [10 + i for i in range(20)]
        handle, masked = link.select(np.array([12, 29, 10, 11]))
        assert len(handle) == 16 and masked.shape == (4, 3)


@pytest.mark.parametrize("data, code", BAD_FRAMES,
                         ids=["oversize", "garbage", "version", "unknown_type", "missing"])
def test_bad_frames_are_refused_and_the_daemon_serves_on(daemon, tls_dir, data, code):
    with contextlib.closing(raw(daemon.address, tls_dir)) as sock:
        assert hello(sock)["t"] == "capabilities"
        sock.sendall(data)
        reply = read_msg(sock)
        assert reply["t"] == "error" and reply["code"] == code
        assert read_msg(sock) is None
    assert_serves(daemon, tls_dir)


def _send(sock, kind: str, **fields) -> dict:
    sock.sendall(encode_bytes(messages.make(kind, **fields)))
    return read_msg(sock)


def test_messages_out_of_place_are_named(daemon, tls_dir):
    invocation = {"sid": SID, "count": 96, "evaluator": "127.0.0.1:1"}
    with contextlib.closing(raw(daemon.address, tls_dir)) as sock:  # a device
        hello(sock)
        reply = _send(sock, "map_invocation", **invocation)
        assert reply["code"] == errors.UNEXPECTED and "map_invocation" in reply["message"]
    with contextlib.closing(raw(daemon.address, tls_dir)) as sock:
        hello(sock)
        reply = _send(sock, "ot_ext_u", start=0, m=5, u=bytes(128))
        assert reply["code"] == errors.UNEXPECTED and "base OTs" in reply["message"]
    with contextlib.closing(raw(daemon.address, tls_dir, "garbler")) as sock:
        hello(sock, "garbler")
        reply = _send(sock, "map_invocation", **invocation)  # no evaluator allowed
        assert reply["code"] == errors.FORBIDDEN and "'evaluator'" in reply["message"]
        assert reply["sid"] == SID
        reply = _send(sock, "ot_ext_y", sid=SID, start=0, y=bytes(32))  # link lives on
        assert reply["code"] == errors.UNEXPECTED and "ot_ext_y" in reply["message"]
    with contextlib.closing(raw(daemon.address, tls_dir, "garbler")) as sock:
        hello(sock, "garbler")  # the device's request, from the garbler
        reply = _send(sock, "pad_correction_request", frame=bytes(16), sid=SID)
        assert reply["code"] == errors.UNEXPECTED and "pad_correction" in reply["message"]
    with contextlib.closing(raw(daemon.address, tls_dir, "evaluator")) as sock:
        reply = hello(sock, "evaluator")
        assert reply["code"] == errors.FORBIDDEN
    assert_serves(daemon, tls_dir)


def test_a_selection_of_ragged_size_and_a_wrong_count_are_named(daemon, tls_dir):
    with MapOwnerLink(daemon.address, tls_dir) as link:
        link.open()
        conn = link._conn
        conn.write(messages.make("ot_ext_u", start=0, m=7, u=bytes(128)))  # 5 per query
        reply = link._loop.run_until_complete(conn.recv(10))[0]
        assert reply["t"] == "error" and reply["code"] == errors.BAD_REQUEST
        assert "'m'" in reply["message"]
    with contextlib.closing(raw(daemon.address, tls_dir, "garbler")) as sock:
        hello(sock, "garbler")
        reply = _send(sock, "map_invocation", sid=SID, count=95, evaluator="127.0.0.1:1")
        assert reply["code"] == errors.BAD_REQUEST and "'count'" in reply["message"]
        assert "multiple of 96" in reply["message"]  # a point's pad is 96 bits
    assert_serves(daemon, tls_dir)


def test_a_correction_names_the_unknown_frame_or_session(daemon, tls_dir):
    """A run's pad correction needs a frame this map owner selected and a session whose
    OT it took: either missing is named, and the link serves on."""
    with MapOwnerLink(daemon.address, tls_dir) as link:
        link.open()
        handle, _ = link.select(np.array([10, 11, 12, 13]))
        conn = link._conn
        for frame, field in ((bytes(16), "'frame'"), (handle, "'sid'")):
            conn.write(messages.make("pad_correction_request", frame=frame, sid=SID))
            reply = link._loop.run_until_complete(conn.recv(10))[0]
            assert reply["t"] == "error" and reply["code"] == errors.BAD_REQUEST
            assert field in reply["message"] and reply["sid"] == SID
        assert link.select(np.array([10, 11, 12, 13]))[0] != handle  # served on
    assert_serves(daemon, tls_dir)


def test_the_map_owner_sends_labels_only_to_evaluators_its_operator_allowed(
        tmp_path, daemon, tls_dir):
    """The garbler names the evaluator replica of each invocation; the map owner dials it
    only if its own --evaluator names reach it: none allowed, or another address, is
    ``forbidden`` before any OT or connection."""
    target = Listener()
    (tmp_path / "map.json").write_text(json.dumps(MAP))
    allowed = start_daemon("mapd", ["--map", str(tmp_path / "map.json"), "--tls-dir",
                                    str(tls_dir), "--evaluator", f"127.0.0.2:{target.port}"],
                           tmp_path / "mapd.log")
    try:
        for running, words in ((daemon, "dials no evaluator"),
                               (allowed, f"127.0.0.1:{target.port} is not an evaluator "
                                         f"this server may dial")):
            with contextlib.closing(raw(running.address, tls_dir, "garbler")) as sock:
                hello(sock, "garbler")
                reply = _send(sock, "map_invocation", sid=SID, count=384,
                              evaluator=f"127.0.0.1:{target.port}")
                assert reply["code"] == errors.FORBIDDEN, reply
                assert words in reply["message"] and "--evaluator" in reply["message"]
        assert target.dialled() == 0
    finally:
        allowed.stop()
        target.close()


ORPHAN_STARTER = """
import sys, time
from pathlib import Path
from snail_client.embedded import start_daemon

mapd = start_daemon("mapd", ["--map", sys.argv[1], "--tls-dir", sys.argv[2]],
                    Path(sys.argv[3]))
print(mapd.process.pid, flush=True)
time.sleep(600)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_local_map_owner_ends_with_its_starter(tmp_path, tls_dir):
    (tmp_path / "map.json").write_text(json.dumps(MAP))
    starter = subprocess.Popen([sys.executable, "-c", ORPHAN_STARTER,
                                str(tmp_path / "map.json"), str(tls_dir),
                                str(tmp_path / "mapd.log")], stdout=subprocess.PIPE, text=True)
    try:
        pid = int(starter.stdout.readline())
    finally:
        starter.send_signal(signal.SIGKILL)
        starter.wait()
    deadline = time.monotonic() + 60  # a hang guard
    while _running(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = _running(pid)
    if alive:
        os.kill(pid, signal.SIGKILL)
    assert not alive, "snail-mapd outlived its SIGKILLed starter"


def _running(pid: int) -> bool:
    """Alive and not a zombie."""
    try:
        return "\nState:\tZ" not in Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False
