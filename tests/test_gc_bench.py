"""``snail-bench engine`` runs end to end (garbler and evaluator processes included) and
prints the documented shape; a small configuration keeps it a smoke test."""

import os

import pytest

from snail_bench.engine import available_engines, engine_report
from snail_common.gc import engine as engines

RATES = ("aes_blocks_per_s", "garble_and_per_s", "evaluate_and_per_s", "end_to_end_and_per_s")


def test_engine_report_shape_and_sanity():
    report = engine_report(wide_layers=2, deep_layers=20)["engine"]
    assert set(report) >= {"aes_blocks_per_s", "garble_and_per_s", "evaluate_and_per_s",
                           "step_overhead_us", "scheme", "bytes_per_and"}
    assert all(report[k] > 0 for k in RATES)
    assert report["step_overhead_us"] > 0
    # the stream's floor: TLS both ways, the table link's seal both ways and the socket
    # (figures: a rate is the benchmark's to report, never a test's to judge,
    # docs/development.md)
    assert all(report[k] > 0 for k in ("tls_encrypt_bytes_per_s", "tls_decrypt_bytes_per_s",
                                       "table_seal_bytes_per_s", "table_open_bytes_per_s",
                                       "socket_bytes_per_s"))
    assert report["wide_and"] == 2 * (1 << 15)
    assert report["deep_steps"] >= 2 * 20
    assert report["scheme"] == "halfgates" and report["bytes_per_and"] == 32
    three = report["schemes"]["threehalves"]
    assert all(three[k] > 0 for k in RATES[1:])
    # 3 half-labels and 5 control bits per AND, the control bits padded per 8 Ki-gate block
    assert three["bytes_per_and"] == pytest.approx(24.625, abs=0.01)
    assert report["bytes_ratio"] == pytest.approx(197 / 256, abs=1e-3)


def test_each_engine_in_the_same_run():
    """Both engines where the native kernel can run: each its own entry, the same stream
    bytes, the top-level fields those of the engine the daemons would serve with."""
    names = available_engines()
    report = engine_report(wide_layers=1, deep_layers=4, schemes=("halfgates",))["engine"]
    assert tuple(report["engines"]) == names
    for name, entry in report["engines"].items():
        assert entry["engine"] == name and all(entry[k] > 0 for k in RATES[1:])
        assert entry["stream_bytes"] == report["stream_bytes"]
    assert report["engine"] == report["serving"] == engines.resolve()
    assert report["garble_and_per_s"] == report["engines"][report["engine"]][
        "garble_and_per_s"]
    numpy_only = engine_report(wide_layers=1, deep_layers=4, schemes=("halfgates",),
                               engine_names=("numpy",))["engine"]
    assert set(numpy_only["engines"]) == {"numpy"} and numpy_only["engine"] == "numpy"
    with pytest.raises(ValueError, match="engines"):
        engine_report(wide_layers=1, deep_layers=4, engine_names=("gpu",))


def test_one_scheme_at_the_top():
    report = engine_report(wide_layers=1, deep_layers=4, schemes=("threehalves",))["engine"]
    assert report["scheme"] == "threehalves" and set(report["schemes"]) == {"threehalves"}
    assert "bytes_ratio" not in report
    with pytest.raises(ValueError, match="schemes"):
        engine_report(wide_layers=1, deep_layers=4, schemes=("quarter",))


def test_the_kernel_threads_are_in_the_report(monkeypatch):
    """A figure on two cores says so; the variable is restored; a bad count is refused."""
    monkeypatch.delenv("SNAIL_KERNEL_THREADS", raising=False)
    names = available_engines()[:1]
    report = engine_report(wide_layers=1, deep_layers=4, schemes=("halfgates",),
                           engine_names=names, threads=2)["engine"]
    assert report["kernel_threads"] == 2 and all(report[k] > 0 for k in RATES)
    assert "SNAIL_KERNEL_THREADS" not in os.environ
    assert engine_report(wide_layers=1, deep_layers=4, schemes=("halfgates",),
                         engine_names=names)["engine"]["kernel_threads"] == 1
    with pytest.raises(ValueError, match=r"threads must be an integer in 1\.\.2"):
        engine_report(wide_layers=1, deep_layers=4, threads=3)
