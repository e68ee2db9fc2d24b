"""How ``snail-bench service`` ends, with and without --map-points: the report as one JSON
object (--json) or as lines, and a service that fails as exit 1 naming why. The
measurements are stood in for here (test_service_bench.py runs the real ones)."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from snail_bench import mapowner, service
from snail_bench.cli import main
from snail_client.links import ServiceError

SERVICE = {"service": {"lm-sil-ldlt-n4": {
    "median_s": 0.25, "min_s": 0.2, "max_s": 0.5, "first_s": 1.5, "and": 123_456,
    "traffic": {"garbler_to_evaluator": 4_200_000}, "peak_rss_mb": {"garbler": 90},
    "clients": 3, "client_median_s": [0.3, 0.4, 0.35], "throughput_inv_per_s": 7.5}}}
MAP_OWNER = {"map_owner": {"lm-sil-ldlt-n6": {"64": {
    "median_s": 0.75, "plain_circuit": "lm-sil-ldlt-n6", "plain_frame_median_s": 0.5,
    "and": 2_000_000, "plain_and": 1_500_000,
    "pad_ot": {"map_owner_s": 0.01, "mapowner_to_garbler": 5_000, "garbler_to_mapowner": 6_000},
    "selection": {"map_owner_s": 0.02, "bytes_to_device": 7_000},
    "pose_equals_cleartext": True}}}}
SERVICE_LINES = [
    "      lm-sil-ldlt-n4: median 0.250 s (min 0.200, max 0.500, first 1.500)  4.2 MB "
    "garbler->evaluator  123,456 AND  peak RSS garbler 90 MB",
    "                      3 clients: 7.5 invocations/s in total, slowest client's median "
    "0.400 s",
]
MAP_OWNER_LINES = [
    "      lm-sil-ldlt-n6 M=     64: median 0.750 s/iteration (first setting, lm-sil-ldlt-n6: "
    "0.500 s)  2,000,000 AND (plain 1,500,000; selection 0)  pad OT 0.01 s, 5,000 B up / "
    "6,000 B down per iteration  selection 0.02 s, 7,000 B per frame  pose == cleartext: True",
]
# (arguments, where the report comes from, the report, its lines)
RUNS = {
    "service": (["--points", "4", "--solve", "circuit"], (service, "service_report"),
                SERVICE, SERVICE_LINES),
    "map_owner": (["--points", "6", "--map-points", "64"], (mapowner, "map_owner_report"),
                  MAP_OWNER, MAP_OWNER_LINES),
}


def _run(monkeypatch, which: str, outcome, *extra: str):
    args, (module, name), _, _ = RUNS[which]

    def measure(*_args, **_kwargs):
        if isinstance(outcome, Exception):
            raise outcome
        return outcome

    monkeypatch.setattr(module, name, measure)
    return CliRunner().invoke(main, ["-q", "service", *args, *extra])


@pytest.mark.parametrize("which", RUNS)
def test_the_report_prints_as_json_or_as_lines(monkeypatch, which):
    report, lines = RUNS[which][2:]
    result = _run(monkeypatch, which, report, "--json")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout) == report
    result = _run(monkeypatch, which, report)
    assert result.exit_code == 0, result.output
    assert result.stdout.splitlines() == lines


@pytest.mark.parametrize("which", RUNS)
def test_a_service_that_fails_is_exit_1_naming_why(monkeypatch, which):
    result = _run(monkeypatch, which, ServiceError("the evaluator went away"), "--json")
    assert result.exit_code == 1
    assert result.stdout == ""
    assert result.stderr == "snail-bench: the evaluator went away\n"
