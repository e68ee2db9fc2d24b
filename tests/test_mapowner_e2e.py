"""The map-owner setting end to end: four processes (this client, the garbler, the
evaluator, snail-mapd) over TLS on loopback.

- A frame's garbled pose equals, bit for bit, the cleartext run of the plain SIL circuit
  on the points the map owner normalized, for maps of 64, 1,000 and 10,000 points.
- Every frame each daemon receives is recorded (a launcher wraps frames.decode), as is
  every frame this client receives: nothing to the map owner carries a 2D point, a map id,
  a pose, a seed or the offset; nothing to the client carries a 3D point (in the clear or
  normalized) or a label of the map owner's wires.
"""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import msgpack
import numpy as np
import pytest
from click.testing import CliRunner
from shared_paths import EXAMPLES
from test_service_e2e import hello, raw, read_msg

from snail_client.blocking import SecureRunner
from snail_client.cli import main as client
from snail_client.embedded import Daemon
from snail_client.links import ServiceError
from snail_client.localize import GarbledBackend
from snail_client.mapowner import MapOwnerLink
from snail_common.circuit import registry
from snail_common.circuit.ir import FIRST_INPUT
from snail_common.families import register_all
from snail_common.loc import mapfile, owner
from snail_common.loc.backends import CircuitBackend
from snail_common.loc.geometry import pose_from_rvec_tvec
from snail_common.loc.pipeline import Options
from snail_common.loc.problem import ProblemError, load_problem
from snail_common.net import errors, frames, messages
from snail_common.net.frames import encode_bytes
from snail_common.net.tls import make_certs

RECORDER = """
import sys, msgpack
import snail_common.net.frames as frames
_decode, _log = frames.decode, open(sys.argv.pop(1), "ab")
def decode(body, lend=False):
    msg = _decode(body, lend)
    kept = {k: v for k, v in msg.items() if not (msg["t"] == "tables" and k == "data")}
    _log.write(msgpack.packb(kept, use_bin_type=True))
    _log.flush()
    return msg
frames.decode = decode
from snail_%s.cli import main
main(prog_name="snail-%s")
"""
OPTIONS = Options(solve="circuit", min_invocations=5)  # padding runs included


def start_recorded(role: str, root: Path, *args: str) -> Daemon:
    """A daemon on loopback that appends every frame it receives to ROLE.frames."""
    log = root / f"{role}.log"
    with open(log, "wb") as err:
        proc = subprocess.Popen([sys.executable, "-c", RECORDER % (role, role),
                                 str(root / f"{role}.frames"), "--listen", "127.0.0.1:0",
                                 "--log-level", "info", *args],
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=err)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        for line in log.read_text().splitlines():
            entry = json.loads(line)
            if entry.get("event") == "listening":
                return Daemon(role, proc, f"127.0.0.1:{entry['port']}", log)
        assert proc.poll() is None, log.read_text()
        time.sleep(0.05)
    proc.kill()
    raise AssertionError(f"the {role} did not start: {log.read_text()}")


def received(root: Path, role: str) -> list[dict]:
    with open(root / f"{role}.frames", "rb") as f:
        return list(msgpack.Unpacker(f, raw=False))


def scene(m: int, example: str = "synthetic_n6"
          ) -> tuple[mapfile.MapPoints, mapfile.Frame, object]:
    """A shared example as a frame, its points hidden among m map points."""
    problem = load_problem(EXAMPLES / f"{example}.json")
    rng = np.random.default_rng(m)
    ids = rng.permutation(1 << 24)[:m].astype(np.int64)
    where = rng.permutation(m)[:problem.n]  # the frame's points anywhere in the map
    xyz = rng.normal(problem.points3d.mean(axis=0), 2.0, (m, 3))
    xyz[where] = problem.points3d
    frame = mapfile.Frame(K=problem.K, dist=problem.dist, points2d=problem.points2d,
                          map_ids=ids[where], initial_pose=problem.initial_pose)
    return mapfile.MapPoints(ids=ids, xyz=xyz), frame, problem


def write_map(points: mapfile.MapPoints, path: Path) -> Path:
    path.write_text(json.dumps({"format": "snail-map/1", "points": [
        {"id": int(i), "xyz": p.tolist()} for i, p in zip(points.ids, points.xyz)]}))
    return path


@pytest.fixture(scope="module")
def servers(tmp_path_factory):
    root = tmp_path_factory.mktemp("servers")
    tls_dir = make_certs(root / "tls")
    evaluator = start_recorded("evaluator", root, "--tls-dir", str(tls_dir))
    yield root, tls_dir, evaluator
    evaluator.stop()


@contextlib.contextmanager
def map_owner(servers, points: mapfile.MapPoints, tmp_path: Path
              ) -> Iterator[tuple[Daemon, Daemon]]:
    """A fresh snail-mapd holding ``points``, then a garbler allowed to dial it (it learns
    the map owner's address at its start, as from its operator); both record what they
    receive in ``tmp_path``."""
    _, tls_dir, evaluator = servers
    mapd = start_recorded("mapd", tmp_path, "--map", str(write_map(points, tmp_path /
                                                                    "map.json")),
                          "--tls-dir", str(tls_dir), "--evaluator", evaluator.address)
    try:
        garbler = start_recorded("garbler", tmp_path, "--evaluator", evaluator.address,
                                 "--map-owner", mapd.address, "--tls-dir", str(tls_dir))
        try:
            yield mapd, garbler
        finally:
            garbler.stop()
    finally:
        mapd.stop()


def run_frame(servers, m: int, tmp_path: Path, example: str = "synthetic_n6"):
    """Localize the example against a map of ``m`` points held by a fresh snail-mapd;
    returns the garbled result, the oracle's, and what the map owner holds."""
    _, tls_dir, evaluator = servers
    points, frame, problem = scene(m, example)
    with map_owner(servers, points, tmp_path) as (mapd, garbler), MapOwnerLink(
            mapd.address, tls_dir) as link, SecureRunner(
                garbler.address, evaluator.address, tls_dir) as runner:
        published = link.open()
        handle, masked = link.select(frame.map_ids)
        runner.use_frame(handle, mapd.address)
        got = owner.localize_shared(frame, published, masked, OPTIONS,
                                    GarbledBackend(runner))
        traffic = {**runner.totals, **link.traffic}
    published, values = owner.owner_values(points)
    want = owner.localize_known(frame, published, values, OPTIONS, CircuitBackend())
    return got, want, (frame, problem, values, traffic)


@pytest.mark.parametrize("m", [64, 1000, 10_000])
def test_the_pose_equals_the_cleartext_runs_bit_for_bit(servers, tmp_path, m):
    got, want, (_, problem, _, traffic) = run_frame(servers, m, tmp_path)
    assert np.array_equal(got.rvec, want.rvec) and np.array_equal(got.tvec, want.tvec)
    assert got.cost == want.cost and got.iterations == want.iterations
    assert got.invocations == OPTIONS.min_invocations  # padded as in the first setting
    assert got.converged and got.rms_px < 1.0
    # the first setting's pose on the same data, to float32 noise
    ref = pose_from_rvec_tvec(problem.reference_pose.rvec, problem.reference_pose.tvec)
    assert np.linalg.norm(pose_from_rvec_tvec(got.rvec, got.tvec).t - ref.t) < 0.05
    assert traffic["client_to_mapowner"] < 2_000 + 64 * m.bit_length()
    assert traffic["mapowner_to_client"] > 12 * 6 * m  # the whole padded table


@pytest.mark.parametrize("m", [64, 1000, 10_000])
@pytest.mark.parametrize("example", ["apriltag_4corners", "synthetic_n12", "synthetic_n64"])
def test_every_shared_example_up_to_64_points(servers, tmp_path, example, m):
    """With synthetic_n6 above: every shared example up to n = 64, in every map size."""
    got, want, _ = run_frame(servers, m, tmp_path, example)
    assert np.array_equal(got.rvec, want.rvec) and np.array_equal(got.tvec, want.tvec)
    assert got.cost == want.cost and got.converged


def _blobs(messages: list[dict]) -> list[bytes]:
    return [v for msg in messages for v in msg.values() if isinstance(v, bytes)]


def _found(needles: set[bytes], blobs: list[bytes]) -> list[bytes]:
    return [n for n in needles if any(n in b for b in blobs)]


def test_no_frame_carries_what_its_receiver_must_not_see(servers, tmp_path, monkeypatch):
    client_got: list[dict] = []
    decode = frames.decode

    def recording(body, lend=False):
        msg = decode(body, lend)
        client_got.append(msg)
        return msg

    root = servers[0]
    earlier = len(received(root, "evaluator"))
    monkeypatch.setattr(frames, "decode", recording)
    got, _, (frame, problem, values, _) = run_frame(servers, 64, tmp_path)
    to_mapd = received(tmp_path, "mapd")
    to_garbler = received(tmp_path, "garbler")
    to_evaluator = received(root, "evaluator")[earlier:]
    assert {m["t"] for m in to_mapd} <= {"hello", "capabilities", "map_info_request",
                                         "ot_base_a", "ot_ext_u", "pad_correction_request",
                                         "map_invocation", "ot_base_b", "ot_ext_y", "bye"}
    # the map owner: no 2D point, map id, pose, seed or offset
    requests = [m for m in to_garbler if m["t"] == "garble_request"]
    assert requests and all("map_owner" in m and "frame" not in m for m in requests)
    secrets_ = {m[k] for m in requests for k in ("seed", "delta")}
    image = np.asarray(frame.points2d)
    needles = {row.astype("<f8").tobytes() for row in image}
    needles |= {row.astype("<f4").tobytes() for row in image}
    needles |= {int(i).to_bytes(4, "little") for i in frame.map_ids}
    needles |= {int(i).to_bytes(8, "little") for i in frame.map_ids}
    for pose in (problem.initial_pose, ):
        needles |= {pose.rvec.astype("<f8").tobytes(), pose.tvec.astype("<f8").tobytes(),
                    pose.tvec.astype("<f4").tobytes()}
    needles |= {got.rvec.astype("<f8").tobytes(), got.tvec.astype("<f8").tobytes()}
    assert not _found(needles | secrets_, _blobs(to_mapd))
    assert _found(secrets_, _blobs(to_garbler)) and _found(  # the search does find them
        {frame.map_ids[0].astype("<u4").tobytes()}, _blobs(client_got))  # (public list)
    ints = {v for m in to_mapd for v in m.values() if type(v) is int}
    assert not ints & {int(i) for i in frame.map_ids}
    # the evaluator took the map owner's labels; the client never sees one of them
    owner_labels = [m["labels"] for m in to_evaluator if m["t"] == "owner_labels"]
    assert len(owner_labels) == OPTIONS.min_invocations
    labels = {b[i:i + 16] for b in owner_labels for i in range(0, len(b), 16)}
    assert len(labels) == 96 * 6 * OPTIONS.min_invocations
    to_client = [m for m in client_got if m.get("t") != "tables"]
    assert not _found(labels, _blobs(to_client))
    # the client: no 3D point, in the clear or as the map owner holds it
    points = problem.points3d
    needles = {row.tobytes() for row in values}  # normalized float32, the padded values
    needles |= {row.astype("<f8").tobytes() for row in points}
    needles |= {row.astype("<f4").tobytes() for row in points}
    assert {m["t"] for m in client_got} >= {"map_info", "sel_table", "output_labels"}
    assert not _found(needles, _blobs(client_got))


def test_a_frame_the_map_owner_does_not_know_is_refused_by_name(servers, tmp_path):
    _, tls_dir, evaluator = servers
    points, frame, _ = scene(64)
    with map_owner(servers, points, tmp_path) as (mapd, garbler), MapOwnerLink(
            mapd.address, tls_dir) as link, SecureRunner(
                garbler.address, evaluator.address, tls_dir) as runner:
        published = link.open()
        with pytest.raises(ProblemError, match=r"map_ids\[0\]"):
            link.select(np.array([int(published.ids.max()) + 1, *frame.map_ids[1:]]))
        runner.use_frame(bytes(16), mapd.address)  # never issued
        with pytest.raises(ServiceError, match=r"map owner at \S+: field 'frame'"):
            owner.localize_shared(frame, published, np.zeros((6, 3), np.uint32),
                                  OPTIONS, GarbledBackend(runner))


def frame_files(tmp_path: Path, m: int) -> tuple[Path, Path]:
    points, frame, _ = scene(m)
    raw = json.loads((EXAMPLES / "synthetic_n6.json").read_text())
    path = tmp_path / "frame.json"
    path.write_text(json.dumps({"format": "snail-frame/1", "camera": raw["camera"],
                                "points2d": raw["points2d"],
                                "map_ids": [int(i) for i in frame.map_ids],
                                "initial_pose": raw["initial_pose"]}))
    return path, write_map(points, tmp_path / "map.json")


def test_the_command_line_with_a_local_map_owner(tmp_path):
    frame, map_path = frame_files(tmp_path, 64)
    args = ["localize", "--input", str(frame), "--map", str(map_path), "--json",
            "--min-invocations", "3"]
    garbled = CliRunner().invoke(client, args)
    assert garbled.exit_code == 0, garbled.output
    clear = CliRunner().invoke(client, [*args, "--backend", "cleartext"])
    assert clear.exit_code == 0, clear.output
    g, c = json.loads(garbled.stdout), json.loads(clear.stdout)
    assert g["setting"] == "map-owner" and g["status"] == "converged"
    assert (g["rvec"], g["tvec"], g["cost"]) == (c["rvec"], c["tvec"], c["cost"])
    assert g["traffic"]["mapowner_to_client"] > 0 and g["invocations"] >= 3
    # per invocation the garbler answers 576 chosen OTs of two 16-byte labels each
    assert g["traffic"]["garbler_to_mapowner"] >= 32 * 576 * g["invocations"]
    assert g["traffic"]["mapowner_to_garbler"] >= 16 * 576 * g["invocations"]
    assert g["circuit"]["points"] == 6 and g["solve"] == "circuit"


@pytest.mark.parametrize("extra, words", [
    (["--map-owner", "127.0.0.1:1"], "--map-owner and --map"),
    (["--solve", "client"], "--solve circuit"),
    (["--mode", "do"], "--mode sil"),
])
def test_map_owner_flags_that_do_not_fit_are_exit_2(tmp_path, extra, words):
    frame, map_path = frame_files(tmp_path, 64)
    out = CliRunner().invoke(client, ["localize", "--input", str(frame), "--map",
                                      str(map_path), *extra])
    assert out.exit_code == 2 and words in out.output


def test_a_frame_naming_an_id_the_map_lacks_is_exit_2(tmp_path):
    frame, map_path = frame_files(tmp_path, 64)
    data = json.loads(frame.read_text())
    data["map_ids"][2] = 1 << 25  # above every id of the map
    frame.write_text(json.dumps(data))
    out = CliRunner().invoke(client, ["localize", "--input", str(frame), "--map",
                                      str(map_path), "--backend", "cleartext"])
    assert out.exit_code == 2 and "map_ids[2]" in out.stderr
    assert out.stderr.count("\n") == 1


def test_the_evaluator_takes_map_owner_wires_from_the_map_owner_only(servers):
    _, tls_dir, evaluator = servers
    circuit = "loc/lm-sil-ldlt-n6-mo"
    register_all()
    iface = registry.interface(circuit)
    registry.compiled(circuit)  # in the shared cache: the evaluator's load fits the timeout
    everything = FIRST_INPUT + iface.n_inputs
    sid = bytes(range(16))
    with contextlib.closing(raw(evaluator.address, tls_dir)) as sock:
        hello(sock)
        sock.sendall(encode_bytes(messages.make("owner_labels", sid=sid, start=0, total=1,
                                                labels=bytes(16))))
        reply = read_msg(sock)
        assert reply["code"] == errors.UNEXPECTED and "owner_labels" in reply["message"]
    with contextlib.closing(raw(evaluator.address, tls_dir)) as sock:
        hello(sock)
        sock.sendall(encode_bytes(messages.make("session_start", sid=sid, circuit=circuit,
                                                hash=iface.content_hash)))
        sock.sendall(encode_bytes(messages.make("input_labels", sid=sid, start=0,
                                                total=everything,
                                                labels=bytes(16 * everything))))
        reply = read_msg(sock)
        assert reply["t"] == "error" and reply["sid"] == sid
        assert f"needs {everything - 96 * 6} labels" in reply["message"]


def test_a_map_owner_gone_mid_frame_fails_the_run_by_name(servers, tmp_path):
    """The map owner stops after the selection: the next invocation fails at once with an
    error naming the map owner (the pooled link is found dead, a new one is refused), and
    the servers serve the next frame of a live map owner."""
    _, tls_dir, evaluator = servers
    points, frame, _ = scene(64)
    options = Options(solve="circuit", min_invocations=0)
    with map_owner(servers, points, tmp_path) as (mapd, garbler), SecureRunner(
            garbler.address, evaluator.address, tls_dir) as runner:
        with MapOwnerLink(mapd.address, tls_dir) as link:
            published = link.open()
            handle, masked = link.select(frame.map_ids)
        runner.use_frame(handle, mapd.address)
        backend = GarbledBackend(runner)
        owner.localize_shared(frame, published, masked, options, backend)  # links pooled
        mapd.stop()
        with pytest.raises(ServiceError, match="map owner") as gone:
            owner.localize_shared(frame, published, masked, options, backend)
        assert "no result within" not in str(gone.value)  # the lost link's, not a timeout's
        assert runner.health("garbler")["role"] == "garbler"
