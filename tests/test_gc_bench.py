"""``snail-bench engine`` runs end to end (garbler and evaluator processes included) and
prints the documented shape; a small configuration keeps it a smoke test."""

from snail_bench.engine import engine_report

RATES = ("aes_blocks_per_s", "garble_and_per_s", "evaluate_and_per_s", "end_to_end_and_per_s")


def test_engine_report_shape_and_sanity():
    report = engine_report(wide_layers=2, deep_layers=20)["engine"]
    assert set(report) >= {"aes_blocks_per_s", "garble_and_per_s", "evaluate_and_per_s",
                           "step_overhead_us"}
    assert all(report[k] > 0 for k in RATES)
    assert report["step_overhead_us"] > 0
    assert report["wide_and"] == 2 * (1 << 15)
    assert report["deep_steps"] >= 2 * 20
    # one AES call per hashed label: the engine cannot beat the raw AES rate per label
    assert report["evaluate_and_per_s"] < report["aes_blocks_per_s"] / 2
