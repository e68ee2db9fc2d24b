"""Every ``snail-bench`` and ``snail-demo`` subcommand runs as its ``--help`` and the README
write it, at the smallest size, so a crash in a command's own wiring (``engine`` stopped
with ``KeyError: 0`` before any measurement) cannot land again.

What each run checks is only that the command finishes as documented (exit status and the
shape of its report); what the numbers mean is for each command's own tests. Commands
with no size flag (``engine``, ``paper --quick``) run in-process with their sizes shrunk
through the module constants the command reads; the rest run as their own process. The
network lab's commands (``netem``, ``paper``'s lab series) need root: where not root they
are skipped with the reason, and ``fuzz`` without atheris checks its exit 2 instead.
"""

from __future__ import annotations

import functools
import json
import subprocess
import sys

import pytest
from click.testing import CliRunner
from shared_paths import BRISTOL, SHARED

from snail_bench import engine as engine_module
from snail_bench import paper as paper_module
from snail_bench.cli import main as bench
from snail_demo.cli import main as demo

TIMEOUT = 600


def _lab_unavailable() -> str | None:
    from snail_bench.netlab.namespaces import check_capable, netns_list

    try:
        check_capable()
        netns_list()
    except Exception as exc:  # no ip, no netns support, no root
        return f"network lab unavailable: {exc}"
    return None


def _run(module: str, *args: str) -> subprocess.CompletedProcess:
    """The console script's entry point (``MODULE.main``, as pyproject.toml names it) with
    ARGS, as its own process."""
    code = f"import sys; from {module} import main; sys.exit(main())"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True,
                          text=True, timeout=TIMEOUT)


def _json(out: subprocess.CompletedProcess | object, key: str) -> dict:
    text = out.stdout if isinstance(out, subprocess.CompletedProcess) else out.output
    return json.loads(text)[key]


# every subcommand and the test that runs it below (a new command must add one)
COVERED = {
    "bench": {"accuracy", "audits", "bristol", "circuit", "compiler", "engine", "fuzz", "netem",
              "ops", "paper", "service", "soak", "track", "verify-evidence"},
    "demo": {"accuracy", "turbo"},
}


@pytest.mark.parametrize("group, cli", [("bench", bench), ("demo", demo)])
def test_every_subcommand_has_a_smoke_run_and_a_help(group, cli):
    assert set(cli.commands) == COVERED[group]
    for name in cli.commands:
        out = CliRunner().invoke(cli, [name, "--help"])
        assert out.exit_code == 0, (name, out.output)
        assert "Usage:" in out.output and "--help" in out.output


def test_bench_ops():
    out = _run("snail_bench.cli", "ops", "--json")
    assert out.returncode == 0, out.stderr
    assert _json(out, "ops")


def test_bench_circuit_as_the_readme_writes_it():
    out = _run("snail_bench.cli", "circuit", "--algorithm", "lm", "--mode", "sil",
               "--points", "4", "--json")
    assert out.returncode == 0, out.stderr
    assert _json(out, "circuit")["and"] > 0


def test_bench_bristol():
    out = _run("snail_bench.cli", "bristol", str(BRISTOL / "adder64.txt"), "--input", "5",
               "--input", "7", "--json")
    assert out.returncode == 0, out.stderr
    assert _json(out, "bristol")["outputs"] == [12]


def test_bench_compiler():
    out = _run("snail_bench.cli", "compiler", "--gates", "20000", "--json")
    assert out.returncode == 0, out.stderr
    assert _json(out, "compiler")


def test_bench_engine_as_the_readme_writes_it(monkeypatch):
    """``snail-bench engine`` (both schemes, the default), on a small circuit."""
    small = functools.partial(engine_module.engine_report, wide_layers=1, deep_layers=4)
    monkeypatch.setattr(engine_module, "engine_report", small)
    out = CliRunner().invoke(bench, ["engine", "--json"])
    assert out.exit_code == 0, out.output
    report = _json(out, "engine")
    assert report["scheme"] == "halfgates"
    assert set(report["schemes"]) == {"halfgates", "threehalves"}
    one = CliRunner().invoke(bench, ["engine", "--scheme", "threehalves"])
    assert one.exit_code == 0, one.output
    assert "threehalves" in one.output


def test_bench_service():
    out = _run("snail_bench.cli", "-q", "service", "--points", "4", "--repeat", "1",
               "--json")
    assert out.returncode == 0, out.stderr
    assert set(_json(out, "service")) == {"nx-sil-n4"}


def test_bench_audits():
    out = _run("snail_bench.cli", "audits", "--points", "4", "--repeat", "2", "--batches",
               "1", "--audits", "1", "--table-link", "digest")
    assert out.returncode == 0, out.stderr
    assert _json(out, "table_link") == "digest"  # the daemons took the flag, and said so
    report = _json(out, "audits")["loc/nx-sil-n4"]
    assert report["garbler"]["attest_share"]["median"] > 0
    assert report["evaluator"]["digest_gb_per_s"]["median"] > 0
    assert report["client"]["cpu_s_per_audit"]["median"] > 0


def test_bench_verify_evidence_of_no_file(tmp_path):
    """(The real files: tests/test_audits_e2e.py.) One that proves nothing exits 1."""
    path = tmp_path / "e.json"
    path.write_text('{"format": "snail-evidence/1"}')
    out = _run("snail_bench.cli", "verify-evidence", str(path))
    assert out.returncode == 1 and json.loads(out.stdout)["proven"] is False


def test_bench_track():
    out = _run("snail_bench.cli", "-q", "track", "--points", "4", "--frames", "4", "--json")
    assert out.returncode == 0, out.stderr
    entry = _json(out, "track")["nx-sil-n4"]
    assert entry["frames"] == 4 and entry["setting"] == "offload"


def test_bench_soak():
    out = _run("snail_bench.cli", "-q", "soak", "--clients", "1", "--minutes", "0.05",
               "--points", "4", "--min-invocations", "1", "--json")
    assert out.returncode == 0, out.stderr
    assert _json(out, "soak")["ok"]


def test_bench_accuracy():
    out = _run("snail_bench.cli", "-q", "accuracy", "--scenes", "2", "--json")
    assert out.returncode == 0, out.stderr
    assert set(_json(out, "accuracy")) == {"lm", "gn"}


def test_bench_fuzz():
    try:
        import atheris  # noqa: F401
    except ImportError:
        out = _run("snail_bench.cli", "fuzz", "--runs", "1", "--seconds", "1")
        assert out.returncode == 2 and "atheris" in out.stderr, out.stderr
        print("fuzz: atheris is not installed; checked its exit 2 instead of a run")
        return
    out = _run("snail_bench.cli", "fuzz", "--target", "frames", "--runs", "10",
               "--seconds", "5", "--json")
    assert out.returncode == 0, out.stderr
    assert _json(out, "fuzz")["frames"]["ok"]


def test_bench_netem():
    reason = _lab_unavailable()
    if reason:
        print(f"netem: {reason}")
        pytest.skip(reason)
    out = _run("snail_bench.cli", "-q", "netem", "--server-delay-ms", "1", "--points", "4",
               "--repeat", "1", "--no-baseline", "--measure-seconds", "0.2", "--json")
    assert out.returncode == 0, out.stderr
    assert set(_json(out, "netem")["service"]) == {"nx-sil-n4"}


def test_bench_paper_quick(monkeypatch, tmp_path):
    """``snail-bench paper --out DIR --quick`` with a plan of one n = 4 circuit (without
    root its lab series say they were not measured, as the README writes)."""
    pytest.importorskip("matplotlib", reason="the bench extra (matplotlib) is not installed")
    if _lab_unavailable():
        print(f"paper: {_lab_unavailable()}; its lab series are not measured")
    small = paper_module.Plan(totals_points=(4,), do_points=(), sweep_points=(4,),
                              algorithms=("lm",), repeat=1, micro_lanes=8)
    monkeypatch.setattr(paper_module, "QUICK", small)
    monkeypatch.setattr(paper_module, "MIN_INVOCATIONS", 2)
    monkeypatch.setattr(paper_module, "LATENCY_DELAYS_MS", (0.0, 5.0))
    out = CliRunner().invoke(bench, ["-q", "paper", "--out", str(tmp_path), "--quick",
                                     "--paper-results", str(SHARED / "paper_results.json")])
    assert out.exit_code == 0, out.output
    assert (tmp_path / "report.md").exists() and (tmp_path / "results.json").exists()


def test_demo_accuracy():
    out = _run("snail_demo.cli", "-q", "accuracy", "--frames", "1", "--json")
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["frames"] == 1


def test_demo_turbo(tmp_path):
    """``snail-demo turbo --out DIR --backend cleartext`` for one control step: it misses
    the target (exit 3, as documented) but writes its log, video and plot."""
    out = _run("snail_demo.cli", "-q", "turbo", "--out", str(tmp_path), "--backend",
               "cleartext", "--min-invocations", "1", "--max-steps", "1")
    assert out.returncode == 3, out.stderr
    assert "missed the target" in out.stdout
    assert {p.name for p in tmp_path.iterdir()} >= {"turbo.json", "turbo.mp4",
                                                    "trajectory.png"}
