"""``snail-bench service`` measures real secure runs: its byte counts are what half-gates
must send, its wall times are ordered, and the servers it starts report their memory."""

import json
import subprocess
import sys

from snail_common.circuit import registry
from snail_common.pnp.spec import Spec

LABEL_BYTES = 16


def _bench(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "snail_bench.cli", "service", *args],
                          capture_output=True, text=True, timeout=300)


def test_service_bench_reports_measured_runs():
    out = _bench("--points", "4", "--repeat", "2", "--json")
    assert out.returncode == 0, out.stderr
    row = json.loads(out.stdout)["service"]["ne-sil-n4"]  # the client solves, by default
    iface = registry.interface(Spec(solver="client", points=4).registry_id)
    assert (row["and"], row["depth"], row["repeat"]) == (iface.counts["and"], iface.depth, 2)
    assert 0 < row["min_s"] <= row["median_s"] <= row["max_s"]
    assert row["first_s"] > 0
    traffic = row["traffic"]
    # half-gates: two ciphertexts per AND gate, plus frame headers
    assert 2 * LABEL_BYTES * iface.counts["and"] <= traffic["garbler_to_evaluator"] \
        < 1.01 * 2 * LABEL_BYTES * iface.counts["and"] + 64_000
    # the client sends one active label per input wire to the evaluator, none to the garbler
    assert traffic["client_to_evaluator"] >= LABEL_BYTES * iface.n_inputs
    assert traffic["client_to_garbler"] < 1_000
    assert all(traffic[k] >= LABEL_BYTES * iface.n_outputs
               for k in ("evaluator_to_client", "garbler_to_client"))
    assert row["timing"]["garbler_garble_s"] > 0 and row["timing"]["evaluator_evaluate_s"] > 0
    assert all(mb > 10 for mb in row["peak_rss_mb"].values())
    assert set(row["peak_rss_mb"]) == {"garbler", "evaluator"}


def test_service_bench_half_remote_addresses_is_a_usage_error():
    out = _bench("--points", "4", "--garbler", "127.0.0.1:1")
    assert out.returncode == 2 and "--tls-dir" in out.stderr


def test_service_bench_measures_a_fleet_with_lanes():
    out = _bench("--points", "4", "--repeat", "2", "--clients", "3", "--lane-window-ms", "50",
                 "--solve", "circuit", "--json")
    assert out.returncode == 0, out.stderr
    row = json.loads(out.stdout)["service"]["lm-sil-ldlt-n4"]
    assert row["clients"] == 3 and len(row["client_median_s"]) == 3
    assert all(m > 0 for m in row["client_median_s"])
    # 6 runs in at least the slowest client's 2 runs' time, and not absurdly fast
    assert 0 < row["throughput_inv_per_s"] <= 6 / max(row["client_median_s"])
    assert row["timing"]["garbler_lanes"] >= 1
