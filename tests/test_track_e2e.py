"""Tracking through real daemons: garbled poses equal the cleartext circuit's bit for
bit with one frame or two in flight and at a constant rate; every frame after the first
makes exactly K runs, a frame with nothing to run included (padding); the command line's
records and summary; the map-owner setting on the same schedule."""

from __future__ import annotations

import itertools
import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from click.testing import CliRunner
from daemons import daemons_with, evaluator_runs, sigint_default

from snail_client.api import Localizer
from snail_client.cli import main as client
from snail_common.loc.problem import problem_to_json
from snail_sim.sequences import handheld

FRAMES = 14
GAP = 6  # this frame has nothing to run (no point in view)


@pytest.fixture(scope="module")
def services(tmp_path_factory):
    yield from daemons_with(tmp_path_factory, "--log-level", "info")


@pytest.fixture(scope="module")
def walk():
    """A short hand-held walk (n = 6) with one frame that has no usable points."""
    seq = handheld(np.random.default_rng(7), 6, FRAMES, map_points=600)
    frames = list(seq.problems)
    frames[GAP] = (np.zeros((2, 2)), np.zeros((2, 3)))  # two points: nothing to run
    return seq, frames


def _track(services, frames, backend: str, **kw) -> list:
    remote = ({"garbler": services.garbler_addr, "evaluator": services.evaluator_addr,
               "tls_dir": str(services.tls_dir)} if backend == "garbled" else {})
    camera = _camera(frames[0])
    with Localizer(camera=camera, backend=backend, **remote, **kw) as loc:
        return list(loc.track(frames))


def _camera(problem):
    from snail_client.inputs.camera import Camera

    return Camera(problem.K, problem.dist, problem.image_size)


def _same(a: list, b: list) -> bool:
    return all(np.array_equal(x.rvec, y.rvec, equal_nan=True)
               and np.array_equal(x.tvec, y.tvec, equal_nan=True) for x, y in zip(a, b))


@pytest.mark.parametrize("in_flight", [1, 2])
def test_garbled_tracking_is_the_cleartext_circuit_bit_for_bit(services, walk, in_flight):
    _, frames = walk
    before = len(evaluator_runs(services))
    garbled = _track(services, frames, "garbled", in_flight=in_flight)
    clear = _track(services, frames, "cleartext", in_flight=in_flight)
    assert len(garbled) == FRAMES and _same(garbled, clear)
    assert [p.status for p in garbled[:2]] == ["converged", "tracked"]
    assert garbled[GAP].status == "failed" and np.isnan(garbled[GAP].rvec).all()
    runs = [p.record["runs"] for p in garbled]
    assert runs[0] == 20 and runs[1:] == [1] * (FRAMES - 1)  # the gap too: padding
    assert [p.record["runs"] for p in clear][GAP] == 0  # no servers: nothing to hide
    assert [p.record["track_status"] for p in garbled][GAP:GAP + 2] == ["lost", "relocalized"]
    assert not any(p.record["revealed"] for p in garbled)
    assert all(p.record["latency_s"] > 0 for p in garbled)
    # the servers ran exactly those runs: 20 + 1 a frame, the gap's padding run included
    assert len(evaluator_runs(services)) - before == 20 + FRAMES - 1


def test_frames_in_flight_start_from_the_frame_d_before(services, walk):
    """Two in flight: frame t starts from frame t-2's answer, so the poses differ from
    one in flight (and the garbled ones still equal the cleartext ones, above)."""
    _, frames = walk
    one = _track(services, frames[:GAP], "cleartext", in_flight=1)
    two = _track(services, frames[:GAP], "cleartext", in_flight=2)
    assert _same(one[:2], two[:2]) and not _same(one[2:], two[2:])


def test_a_constant_rate_pads_the_slots_no_frame_takes(services, walk, tmp_path):
    """--rate: padding runs fill the ticks between frames; the poses are unchanged."""
    _, frames = walk
    seq = tmp_path / "seq.jsonl"
    seq.write_text("".join(json.dumps(problem_to_json(p)) + "\n" for p in frames[:GAP]))
    remote = ["--garbler", services.garbler_addr, "--evaluator", services.evaluator_addr,
              "--tls-dir", str(services.tls_dir)]
    before = len(evaluator_runs(services))
    out = CliRunner().invoke(client, ["track", "--input", str(seq), "--rate", "40",
                                      "--json", *remote])
    assert out.exit_code == 0, out.output
    lines = [json.loads(line) for line in out.stdout.splitlines()]
    records, summary = lines[:-1], lines[-1]["summary"]
    assert summary["rate"] == 40 and summary["frames"] == GAP
    ran = len(evaluator_runs(services)) - before
    assert ran == 20 + (GAP - 1) + summary["paced_padding_runs"]
    clear = _track(services, frames[:GAP], "cleartext")
    assert [r["rvec"] for r in records] == [p.rvec.tolist() for p in clear]


def test_the_command_line_writes_records_and_a_summary(services, walk, tmp_path):
    seq_obj, _ = walk
    seq = tmp_path / "seq.jsonl"
    seq.write_text("".join(json.dumps(problem_to_json(p)) + "\n"
                           for p in seq_obj.problems[:5]))
    out_file = tmp_path / "out.json"
    remote = ["--garbler", services.garbler_addr, "--evaluator", services.evaluator_addr,
              "--tls-dir", str(services.tls_dir)]
    out = CliRunner().invoke(client, ["track", "--input", str(seq), "--runs-per-frame", "2",
                                      "--json", "--output", str(out_file), *remote])
    assert out.exit_code == 0, out.output
    lines = [json.loads(line) for line in out.stdout.splitlines()]
    summary = lines[-1]["summary"]
    assert summary["frames"] == 5 and summary["runs_per_frame"] == 2
    assert summary["runs_first_frame"] == 20 and summary["runs_after_first"] == [2]
    assert set(summary["latency_s"]) == {"p50", "p95", "max"}
    assert summary["lost"] == 0 and summary["revealed"] == 0 and summary["fps"] > 0
    written = json.loads(out_file.read_text())
    assert [r["frame"] for r in written] == list(range(5))
    for record in written:
        assert {"runs", "latency_s", "track_status", "revealed", "prediction"} <= set(record)
    assert written[0]["prediction"] is None  # the padded first frame starts on its own
    assert sum(summary["predictions"].values()) == 4
    assert set(summary["predictions"]) <= {"last-pose", "constant-velocity"}
    human = CliRunner().invoke(client, ["track", "--input", str(seq), *remote])
    assert human.exit_code == 0 and "frames/s" in human.stdout and "the servers saw" in \
        human.stdout


def test_the_map_owner_setting_tracks_on_the_same_schedule(walk, tmp_path):
    """--map with track: the garbled poses equal the cleartext ones on the map owner's
    points, the first frame padded and two runs a frame after it (the device checks a
    fit only where a run evaluated it: with two, the first step's pose)."""
    seq, _ = walk
    map_path = tmp_path / "map.json"
    map_path.write_text(json.dumps({"format": "snail-map/1", "points": [
        {"id": i + 1, "xyz": p.tolist()} for i, p in enumerate(seq.world)]}))
    frames = tmp_path / "frames.jsonl"
    rows = []
    for k, problem in enumerate(seq.problems[:4]):
        row = {"format": "snail-frame/1", **{key: problem_to_json(problem)[key]
                                             for key in ("camera", "points2d")},
               "map_ids": (seq.ids[k] + 1).tolist()}
        if k == 0:
            row["initial_pose"] = problem_to_json(problem)["initial_pose"]
        rows.append(json.dumps(row))
    frames.write_text("\n".join(rows) + "\n")
    results = {}
    for backend in ("garbled", "cleartext"):
        out = CliRunner().invoke(client, ["track", "--input", str(frames), "--map",
                                          str(map_path), "--solve", "circuit", "--backend",
                                          backend, "--runs-per-frame", "2", "--json"])
        assert out.exit_code == 0, out.output
        results[backend] = [json.loads(line) for line in out.stdout.splitlines()][:-1]
    garbled = results["garbled"]
    assert [r["runs"] for r in garbled] == [20, 2, 2, 2]
    assert all(r["setting"] == "map-owner" for r in garbled)
    assert [r["status"] for r in garbled] == ["converged", "tracked", "tracked", "tracked"]
    assert [(r["rvec"], r["tvec"]) for r in garbled] == [
        (r["rvec"], r["tvec"]) for r in results["cleartext"]]



def test_a_constant_rate_runs_on_through_a_pause_in_the_frames(services, walk):
    """--rate: the servers see runs at the rate while the camera pauses (padding), so
    the gap between runs never shows the pause; without it, the pause shows. (Bounds
    relative to the test's own pause: a run would have to take half of it, 60 times its
    time on an idle core, for padding not to split it: docs/development.md.)"""
    _, frames = walk
    pause_s = 1.5

    def paused(rate: float | None) -> float:
        def camera():
            for k, frame in enumerate(frames[:GAP]):
                if k == 3:
                    time.sleep(pause_s)
                yield frame

        before = len(evaluator_runs(services))
        remote = {"garbler": services.garbler_addr, "evaluator": services.evaluator_addr,
                  "tls_dir": str(services.tls_dir)}
        with Localizer(camera=_camera(frames[0]), rate=rate, **remote) as loc:
            assert len(list(loc.track(camera()))) == GAP
        starts = sorted(run["timeline"]["labels"]
                        for run in evaluator_runs(services)[before:])
        return max(b - a for a, b in itertools.pairwise(starts))

    assert paused(None) >= pause_s
    assert paused(40.0) < pause_s / 2  # ticks every 25 ms, padding when no frame waits


def test_ctrl_c_in_a_track_is_one_line_exit_130_and_keeps_the_frames(tmp_path):
    long = handheld(np.random.default_rng(9), 6, 3000)
    seq = tmp_path / "long.jsonl"
    seq.write_text("".join(json.dumps(problem_to_json(p)) + "\n" for p in long.problems))
    out_file = tmp_path / "out.json"
    proc = subprocess.Popen([sys.executable, "-m", "snail_client", "track", "--input",
                             str(seq), "--output", str(out_file), "-q"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=sigint_default)
    first = proc.stdout.readline()  # the embedded servers are up and frames under way
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    out = first + out
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith("snail-client: interrupted after ")
    written = json.loads(out_file.read_text())
    assert 0 < len(written) == len(out.splitlines()) < 3000
