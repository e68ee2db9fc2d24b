"""snail-client localize through real daemons (separate processes, TLS): the garbled
result is bit-identical to the cleartext circuit's, padding reaches --min-invocations,
traffic is measured, and bad input exits 2 naming the field."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest
from shared_paths import EXAMPLES
from table_floor import table_floor

from snail_client.blocking import SecureRunner
from snail_client.embedded import embedded_services
from snail_client.localize import GarbledBackend, Options, localize
from snail_common.circuit import registry
from snail_common.loc.backends import CircuitBackend, Float64Backend
from snail_common.loc.problem import load_problem
from snail_common.loc.reference import reprojection_rms

ALL_EXAMPLES = sorted(path.name for path in EXAMPLES.glob("*.json"))


@pytest.fixture(scope="module")
def runner():
    with embedded_services() as services, SecureRunner(
            services.garbler_addr, services.evaluator_addr, services.tls_dir) as secure:
        yield GarbledBackend(secure)


@pytest.mark.parametrize("name", ALL_EXAMPLES)
def test_garbled_pose_equals_cleartext_pose(runner, name):
    problem = load_problem(EXAMPLES / name)
    garbled = localize(problem, Options(backend="garbled", min_invocations=0), runner)
    clear = localize(problem, Options(backend="cleartext"), CircuitBackend())
    assert garbled["rvec"] == clear["rvec"] and garbled["tvec"] == clear["tvec"]
    assert garbled["cost"] == clear["cost"] and garbled["converged"]
    assert garbled["invocations"] == clear["invocations"] >= garbled["iterations"]
    assert garbled["traffic"]["garbler_to_evaluator"] >= table_floor(garbled)


def test_session_is_padded_to_min_invocations(runner):
    problem = load_problem(EXAMPLES / "synthetic_n6.json")
    result = localize(problem, Options(backend="garbled", min_invocations=7), runner)
    assert result["invocations"] == 7 > result["iterations"]
    assert len(result["timing"]["per_iteration_s"]) < 7  # padding is not an iteration


def test_do_mode_garbled_equals_cleartext_in_one_invocation(runner):
    """The data-oblivious baseline (2 iterations here, 20 by default): one secure run per
    frame, not padded to min_invocations, bit-identical to the cleartext circuit, and
    better than the start."""
    problem = load_problem(EXAMPLES / "apriltag_4corners.json")
    garbled = localize(problem, Options(mode="do", do_iterations=2), runner)
    clear = localize(problem, Options(mode="do", do_iterations=2, backend="cleartext"),
                     CircuitBackend())
    assert garbled["rvec"] == clear["rvec"] and garbled["tvec"] == clear["tvec"]
    assert garbled["cost"] == clear["cost"]
    assert garbled["mode"] == "do" and garbled["iterations"] == 2
    assert garbled["invocations"] == 1 and len(garbled["timing"]["per_iteration_s"]) == 1
    assert garbled["traffic"]["garbler_to_evaluator"] >= table_floor(garbled)
    initial = reprojection_rms(problem, problem.initial_pose.rvec, problem.initial_pose.tvec)
    assert garbled["rms_px"] < 0.5 * initial


def test_the_garbled_client_never_holds_a_netlist(runner, monkeypatch):
    """A client (a phone, a drone) encodes, decodes and names circuits from their small
    interface; compiling and scheduling is the servers' job. An audit is the exception
    (the client garbles the run again from its seed, audit.py), so none is drawn here:
    with the default 1 in 8, one of its three runs is audited a third of the time."""
    def refuse(*_):
        raise AssertionError("the client compiled a circuit")

    monkeypatch.setattr(runner.secure.audits, "draw", lambda: False)
    monkeypatch.setattr(registry, "compiled", refuse)
    monkeypatch.setattr(registry, "lookup", lambda _: None)  # no netlist in memory to use
    registry._interface.cache_clear()
    problem = load_problem(EXAMPLES / "synthetic_n12.json")
    result = localize(problem, Options(backend="garbled", min_invocations=0), runner)
    assert result["converged"] and result["circuit"]["and"] > 0


def test_do_mode_reaches_the_sil_pose():
    problem = load_problem(EXAMPLES / "synthetic_n12.json")
    do = localize(problem, Options(mode="do", backend="float64"), Float64Backend())
    sil = localize(problem, Options(backend="float64"), Float64Backend())
    assert do["converged"] and do["iterations"] == 20 and do["invocations"] == 1
    # the SIL driver stops once a step is below its 1e-5 tolerance; DO runs all 20
    np.testing.assert_allclose(do["rvec"], sil["rvec"], atol=1e-5)
    tvec = np.asarray(sil["tvec"])
    assert np.abs(np.asarray(do["tvec"]) - tvec).max() < 1e-5 * np.linalg.norm(tvec)
    assert abs(do["rms_px"] - sil["rms_px"]) < 1e-4


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "snail_client", *args],
                          capture_output=True, text=True, timeout=300)


def test_cli_json_result_float64():
    out = _cli("localize", "--input", str(EXAMPLES / "synthetic_n6.json"),
               "--backend", "float64", "--json")
    assert out.returncode == 0, out.stderr
    record = json.loads(out.stdout)
    assert record["format"] == "snail-result/1" and record["converged"]
    assert record["rms_px"] < 1.0


@pytest.mark.parametrize(("patch", "field"), [
    ({"points2d": [[1.0, 2.0]] * 3, "points3d": [[0.0, 0.0, 1.0]] * 3}, "points2d"),
    ({"points3d": "nope"}, "points3d"),
    ({"initial_pose": {"rvec": [0, 0, 0]}}, "initial_pose.tvec"),
])
def test_cli_bad_problem_exits_2_naming_the_field(tmp_path, patch, field):
    problem = json.loads((EXAMPLES / "synthetic_n6.json").read_text())
    problem.update(patch)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(problem))
    out = _cli("localize", "--input", str(path), "--backend", "float64")
    assert out.returncode == 2
    assert field in out.stderr and len(out.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize(("args", "flag"), [
    (("--mode", "do", "--algorithm", "gn"), "--mode"),
    (("--do-iterations", "0"), "--do-iterations"),
])
def test_cli_bad_mode_options_are_usage_errors(args, flag):
    out = _cli("localize", "--input", str(EXAMPLES / "synthetic_n6.json"), "--backend",
               "float64", *args)
    assert out.returncode == 2 and flag in out.stderr


def test_cli_half_remote_addresses_is_a_usage_error():
    out = _cli("localize", "--input", str(EXAMPLES / "synthetic_n6.json"),
               "--garbler", "127.0.0.1:1")
    assert out.returncode == 2 and "--tls-dir" in out.stderr


def test_cli_summary_reports_the_median_timed_call():
    out = _cli("localize", "--input", str(EXAMPLES / "synthetic_n6.json"),
               "--backend", "float64")
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 3 and "converged after" in lines[1]
    total, calls, median, first = re.search(
        r"time ([\d.]+) s; (\d+) timed calls, median ([\d.]+) s, first ([\d.]+) s",
        lines[2]).groups()
    assert int(calls) >= 2
    # every call is part of the frame's time: a median above it would be mislabelled
    assert float(median) * int(calls) <= float(total) + 0.01
    assert float(first) <= float(total) + 0.01
