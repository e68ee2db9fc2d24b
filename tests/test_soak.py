"""``snail-bench soak``: a short real soak (client processes, real daemons, every frame
checked against the cleartext backend) reports the FORMATS shape with zero wrong results;
the arithmetic behind the report (percentiles, minute buckets, the flatness rule, the
exit verdict) and the wrong-result check are pinned on synthetic samples."""

from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter

import numpy as np
import pytest

from snail_bench.soak import check_frame, failure_kind
from snail_bench.soak_report import (
    Plan,
    Sample,
    Tally,
    bucket,
    daemon_log,
    flat,
    minute_of,
    per_minute_max,
    percentiles,
    summarize,
)
from snail_client.links import ServiceError
from snail_client.localize import Options, localize
from snail_common.loc.backends import CircuitBackend
from snail_common.loc.synthetic import random_scene


def test_short_soak_reports_checked_frames_and_the_daemons_footprint(tmp_path):
    pytest.importorskip("matplotlib")
    out = subprocess.run(
        [sys.executable, "-m", "snail_bench.cli", "-q", "soak", "--clients", "2",
         "--minutes", "0.3", "--points", "4", "--points", "6", "--min-invocations", "4",
         "--sample-seconds", "1", "--out", str(tmp_path), "--json"],
        capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    body = json.loads(out.stdout)["soak"]
    assert json.loads((tmp_path / "soak.json").read_text())["soak"]["invocations"] \
        == body["invocations"]
    assert (tmp_path / "soak.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert {"invocations", "wrong", "failures", "latency_s", "rss_mb", "fds"} <= set(body)
    assert body["wrong"] == 0 and body["unexplained_failures"] == 0 and body["ok"]
    assert body["frames"] >= 1  # at least one checked: how many is the machine's speed
    assert body["invocations"] + body["wind_down"]["invocations"] >= 4 * body["frames"]
    assert sum(body["invocations_per_minute"]) == body["invocations"]
    lat = body["latency_s"]
    assert 0 < lat["p50"] <= lat["p95"] <= lat["p99"]
    for what in ("rss_mb", "fds"):
        assert set(body[what]) == {"garbler", "evaluator"}
        assert all(len(series) == 1 and series[0] > 0 for series in body[what].values())
    # each daemon holds at least its listening socket and one connection per client link
    assert all(series[0] >= 3 for series in body["fds"].values())
    # one minute: the peaks are not compared, only the footprint after with that before
    assert {k: v for k, v in body["flat_by_series"].items() if not k.startswith("after/")} \
        == dict.fromkeys(("rss_mb/garbler", "rss_mb/evaluator", "fds/garbler",
                          "fds/evaluator"))
    before = body["idle_before"]
    assert all(before[role]["fds"] >= 3 and before[role]["rss_mb"] > 10
               for role in ("garbler", "evaluator"))
    assert body["killed_clients"] == 0
    assert len(body["samples"]["garbler"]) >= 2  # about one a second for ~18 s
    assert max(row[3] for row in body["samples"]["evaluator"]) >= 1  # sessions under way
    after = body["after_clients_left"]  # every session freed once the clients left
    assert after["idle"] and after["fds_back"] and all(
        after[role]["sessions"] == 0 and after[role]["queued_mb"] == 0.0
        and after[role]["rss_mb"] > 10 and after[role]["fds"] > 3
        for role in ("garbler", "evaluator"))
    logs = body["daemon_logs"]
    assert logs["garbler"]["sessions"]["ok"] >= body["invocations"]


def test_a_frame_that_differs_from_cleartext_is_wrong():
    seed, n = 12345, 6
    clear = localize(random_scene(np.random.default_rng(seed), n),
                     Options(backend="cleartext", algorithm="gn"), CircuitBackend())
    assert check_frame(seed, n, "gn", clear, 20) is None
    nudged = dict(clear, cost=float(np.nextafter(clear["cost"], np.inf)))
    wrong = check_frame(seed, n, "gn", nudged, 20)
    assert wrong is not None and set(wrong["fields"]) == {"cost"}
    rotated = dict(clear, rvec=[clear["rvec"][0] + 1e-12, *clear["rvec"][1:]])
    assert set(check_frame(seed, n, "gn", rotated, 20)["fields"]) == {"rvec"}


def test_percentiles_interpolate_and_say_none_for_nothing():
    assert percentiles(list(range(101))) == {"p50": 50.0, "p95": 95.0, "p99": 99.0}
    assert percentiles([2.0, 4.0]) == {"p50": 3.0, "p95": 3.9, "p99": 3.98}
    assert percentiles([]) == {"p50": None, "p95": None, "p99": None}


def test_minutes_bucket_by_time_and_overruns_count_in_the_last():
    assert [minute_of(t, 3) for t in (0.0, 59.9, 60.0, 179.9, 250.0, -1.0)] \
        == [0, 0, 1, 2, 2, 0]
    timed = [(1.0, 5.0), (30.0, 7.0), (61.0, 2.0), (200.0, 9.0)]
    assert bucket(timed, 3) == [[5.0, 7.0], [2.0], [9.0]]
    assert per_minute_max(timed, 4) == [7.0, 2.0, None, 9.0]
    assert Plan(2, 0.3).buckets == 1 and Plan(2, 10).buckets == 10
    assert Plan(2, 2.5).buckets == 3


@pytest.mark.parametrize(("series", "expected"), [
    ([300.0, 100.0, 105.0, 109.9], True),   # the first minute (start-up) is not compared
    ([100.0, 100.0, 90.0], True),
    ([100.0, 100.0, 111.0], False),
    ([100.0, 100.0, 89.0], False),
    ([50.0, 100.0, 60.0, 100.0, 112.0], False),  # only the last minute counts
    ([100.0, 100.0], None),                  # the second minute is the last
    ([100.0, None, 100.0], None),
])
def test_flat_compares_the_last_minute_with_the_second(series, expected):
    assert flat(series) is expected


def _tally(failures: Counter, wrong: int = 0) -> Tally:
    samples = []
    for t in range(0, 250, 2):  # samples after the end (t >= 240) are wind-down
        samples += [Sample(t, "garbler", 200.0 + (t >= 180) * 30 + (t >= 240) * 700, 40,
                           3, 0.0),
                    Sample(t, "evaluator", 300.0, 40 + (t >= 180), None if t < 60 else 5,
                           12.5 * (t // 60))]
    invocations = [(t * 1.5, 0.5 + t / 100) for t in range(100)] + [(241.0, 99.0)] * 7
    return Tally(invocations=invocations, frames=5,
                 wrong=[{"seed": 1}] * wrong, failures=failures, samples=samples)


BEFORE = {"garbler": {"fds": 40, "rss_mb": 200.0}, "evaluator": {"fds": 40, "rss_mb": 300.0}}


def _after(fds: int = 41, garbler_rss: float = 205.0) -> dict:
    return {"idle": True, "fds_back": fds <= 44, "seconds": 1.0,
            "garbler": {"sessions": 0, "queued_mb": 0.0, "rss_mb": garbler_rss, "fds": fds},
            "evaluator": {"sessions": 0, "queued_mb": 0.0, "rss_mb": 300.0, "fds": 40}}


def test_summary_shape_verdicts_and_what_counts_against_the_run():
    body = summarize(_tally(Counter()), Plan(16, 4), 245.0, BEFORE, _after())["soak"]
    assert body["invocations"] == 100 and body["invocations_per_minute"] == [40, 40, 20, 0]
    assert body["wind_down"] == {"seconds": 5.0, "invocations": 7}  # not in the minutes
    assert body["rss_mb"]["garbler"] == [200.0, 200.0, 200.0, 230.0]
    assert body["fds"]["evaluator"] == [40, 40, 40, 41]
    assert body["sessions"] == {"garbler": [3, 3, 3, 3], "evaluator": [None, 5, 5, 5]}
    assert body["queued_mb"]["evaluator"] == [0.0, 12.5, 25.0, 37.5]
    assert body["samples"]["evaluator"][40] == [80, 300.0, 40, 5, 12.5]
    assert body["flat_by_series"] == {
        "rss_mb/garbler": False, "rss_mb/evaluator": True, "fds/garbler": True,
        "fds/evaluator": True, "after/rss_mb/garbler": True, "after/rss_mb/evaluator": True,
        "after/fds/garbler": True, "after/fds/evaluator": True}
    assert body["idle_before"] == BEFORE and body["after_clients_left"] == _after()
    assert body["flat"] is False and body["ok"]  # a leak is reported; exit by results only
    assert body["latency_per_minute_s"]["p50"][3] is None
    assert body["latency_s"]["p50"] == pytest.approx(0.995)
    # busy counts against the run like any failure: a live run must never meet it
    busy = summarize(_tally(Counter(busy=3)), Plan(16, 4), 240.0, BEFORE, _after())["soak"]
    assert busy["failures"] == {"busy": 3} and busy["unexplained_failures"] == 0
    assert not busy["ok"]
    lost = summarize(_tally(Counter(connection=1)), Plan(16, 4), 240.0, BEFORE,
                     _after())["soak"]
    assert lost["unexplained_failures"] == 1 and not lost["ok"]
    assert not summarize(_tally(Counter(), wrong=1), Plan(16, 4), 240.0, BEFORE,
                         _after())["soak"]["ok"]


def test_descriptors_or_memory_not_back_after_the_clients_left_are_not_flat():
    short = Plan(16, 2)  # under three minutes: only after against before counts
    body = summarize(_tally(Counter()), short, 120.0, BEFORE, _after())["soak"]
    assert body["flat"] is True and body["ok"]
    leaked = summarize(_tally(Counter()), short, 120.0, BEFORE, _after(fds=45))["soak"]
    assert leaked["flat_by_series"]["after/fds/garbler"] is False
    assert leaked["flat"] is False and not leaked["ok"]  # descriptors not back: a failure
    grown = summarize(_tally(Counter()), short, 120.0, BEFORE,
                      _after(garbler_rss=221.0))["soak"]
    assert grown["flat"] is False and grown["ok"]  # memory is reported, not an exit


def test_failures_count_under_the_servers_code_or_what_the_client_saw():
    assert failure_kind(ServiceError("evaluator reported busy: full", "busy")) == "busy"
    assert failure_kind(ServiceError("ne-sil-n6: no result within 300 s")) == "client_timeout"
    assert failure_kind(ServiceError("x: integrity check failed, the result was tampered "
                                     "with")) == "integrity"
    assert failure_kind(ServiceError("garbler 127.0.0.1:1: connection lost")) == "connection"
    assert failure_kind(ValueError("bad")) == "client_ValueError"


def test_daemon_logs_are_counted_by_session_outcome_and_trouble(tmp_path):
    log = tmp_path / "garbler.log"
    lines = [{"level": "info", "event": "listening", "port": 1},
             {"level": "info", "event": "session", "outcome": "ok"},
             {"level": "info", "event": "session", "outcome": "ok"},
             {"level": "warning", "event": "session", "outcome": "timeout"},
             {"level": "warning", "event": "connection_refused"},
             {"level": "error", "event": "internal"}]
    log.write_text("\n".join(json.dumps(e) for e in lines) + "\nTraceback (most recent)\n")
    assert daemon_log(log) == {
        "sessions": {"ok": 2, "timeout": 1},
        "warnings": {"warning:connection_refused": 1, "error:internal": 1,
                     "unparsed_line": 1}}
