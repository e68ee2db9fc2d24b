"""``snail-bench service`` measures real secure runs: its byte counts are what half-gates
must send, its wall times are ordered, and the servers it starts report their memory."""

import json
import subprocess
import sys

from table_floor import per_and

from snail_common.circuit import registry
from snail_common.pnp.spec import Spec

LABEL_BYTES = 16


def _bench(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "snail_bench.cli", "service", *args],
                          capture_output=True, text=True, timeout=300)


def test_service_bench_reports_measured_runs():
    # half-gates asked for: auto may pick three-halves once it has measured the link
    out = _bench("--points", "4", "--repeat", "2", "--scheme", "halfgates", "--json")
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["table_link"] == "aead"  # the daemons' default
    row = json.loads(out.stdout)["service"]["nx-sil-n4"]  # the client solves, by default
    assert row["scheme"] == "halfgates"
    iface = registry.interface(Spec(solver="client", points=4, arith="fixed").registry_id)
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


def test_service_bench_sets_only_the_daemons_it_starts():
    out = _bench("--points", "4", "--garbler", "127.0.0.1:1", "--evaluator", "127.0.0.1:2",
                 "--tls-dir", ".", "--table-link", "tls")
    assert out.returncode == 2 and "--table-link sets the embedded daemons" in out.stderr


def test_service_bench_half_remote_addresses_is_a_usage_error():
    out = _bench("--points", "4", "--garbler", "127.0.0.1:1")
    assert out.returncode == 2 and "--tls-dir" in out.stderr


def test_service_bench_measures_a_fleet_with_lanes():
    out = _bench("--points", "4", "--repeat", "2", "--clients", "3", "--lane-window-ms", "50",
                 "--solve", "circuit", "--json")
    assert out.returncode == 0, out.stderr
    row = json.loads(out.stdout)["service"]["lm-sil-ldlt-n4-x"]
    assert row["clients"] == 3 and len(row["client_median_s"]) == 3
    assert all(m > 0 for m in row["client_median_s"])
    # 6 runs in at least the slowest client's 2 runs' time, and not absurdly fast
    assert 0 < row["throughput_inv_per_s"] <= 6 / max(row["client_median_s"])
    assert row["timing"]["garbler_lanes"] >= 1


def test_service_bench_reports_the_map_owner_settings_extra_cost():
    out = _bench("--points", "6", "--map-points", "64", "--repeat", "1", "--json")
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    plain = report["service"]["lm-sil-ldlt-n6-x"]  # the first setting's, same daemons
    row = report["map_owner"]["lm-sil-ldlt-n6-x-mo"]["64"]
    assert (row["points"], row["map_points"], row["repeat"]) == (6, 64, 1)
    assert row["plain_circuit"] == "lm-sil-ldlt-n6-x" and row["plain_and"] == plain["and"]
    assert row["plain_median_s"] == plain["median_s"] > 0
    # the pads come off with free XORs: the same AND gates as the plain circuit
    assert row["and"] == registry.interface("loc/lm-sil-ldlt-n6-x-mo").counts["and"] \
        == plain["and"]
    assert 0 < row["min_s"] <= row["median_s"] <= row["max_s"]
    assert row["timed_iterations"] >= 1 and row["invocations_per_frame"] >= 1
    selection, pad = row["selection"], row["pad_ot"]
    assert selection["and"] == 0 and "no circuit" in selection["how"]
    assert selection["frames"] == 1 and selection["map_owner_s"] > 0
    assert selection["bytes_to_device"] >= 12 * 6 * 64  # every point under a pad
    assert selection["bytes_from_device"] > 0
    assert "snail-mapd session log" in selection["map_owner_s_source"]
    assert pad["ots_per_invocation"] == 96 * 6
    assert pad["sessions"] == row["invocations_per_frame"] and pad["map_owner_s"] > 0
    assert pad["first_s"] > 0 and "session log" in pad["map_owner_s_source"]
    # chosen-message IKNP: 16 bytes a pad bit up, 32 down; the labels 16 each on
    assert pad["mapowner_to_garbler"] >= 16 * 576 and pad["garbler_to_mapowner"] >= 32 * 576
    assert 16 * 576 <= pad["mapowner_to_evaluator"] < 16 * 576 + 2_000
    per_iteration, per_frame = row["traffic_per_iteration"], row["traffic_per_frame"]
    # every AND's tables, in whichever scheme auto picked for each session
    assert per_iteration["garbler_to_evaluator"] >= per_and("threehalves") * plain["and"]
    assert all(per_iteration[k] > 0 for k in per_iteration)
    assert all(per_frame[k] > 0 for k in per_frame)
    assert per_frame["mapowner_to_client"] == selection["bytes_to_device"]
    assert row["pose_equals_cleartext"] and row["status"] == "converged"
    assert row["pose_equals_first_setting"] and row["plain_frame_median_s"] > 0


def test_service_bench_map_points_that_do_not_fit_are_usage_errors():
    for extra in (["--solve", "client"], ["--garbler", "127.0.0.1:1"], ["--clients", "2"]):
        out = _bench("--points", "6", "--map-points", "64", *extra)
        assert out.returncode == 2 and "--map-points" in out.stderr, extra
    out = _bench("--points", "64", "--map-points", "10")
    assert out.returncode == 2 and "must hold" in out.stderr
