"""What a new user meets on the command line: file problems as one line and exit 2, and
defaults that do not surprise (snail-bench service measures n = 6 and 12 unless asked)."""

from __future__ import annotations

import subprocess
import sys

from click.testing import CliRunner
from shared_paths import EXAMPLES

from snail_bench.cli import main as bench
from snail_client.cli import main as client
from snail_common.net.tls import make_certs

N6 = str(EXAMPLES / "synthetic_n6.json")


def test_a_tls_dir_without_the_client_certificate_is_one_line_exit_2(tmp_path):
    out = CliRunner().invoke(client, ["localize", "--input", N6, "--garbler", "127.0.0.1:1",
                                      "--evaluator", "127.0.0.1:2", "--tls-dir",
                                      str(tmp_path)])
    assert out.exit_code == 2
    assert out.stderr.count("\n") == 1 and "client.pem is missing" in out.stderr
    assert "snail-client certs" in out.stderr and "Traceback" not in out.output


def test_a_daemon_with_a_corrupt_certificate_says_which_file(tmp_path):
    make_certs(tmp_path)
    (tmp_path / "garbler.pem").write_text("not a certificate\n")
    out = subprocess.run([sys.executable, "-m", "snail_garbler", "--listen", "127.0.0.1:0",
                          "--evaluator", "127.0.0.1:1", "--tls-dir", str(tmp_path)],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert out.stderr.count("\n") == 1 and "garbler.pem" in out.stderr
    assert "Traceback" not in out.stderr


def test_bench_service_measures_6_and_12_unless_asked(monkeypatch):
    asked = []

    def report(specs, *args):
        asked.extend(spec.points for spec in specs)
        return {"service": {}}

    monkeypatch.setattr("snail_bench.service.service_report", report)
    out = CliRunner().invoke(bench, ["service", "--json"])
    assert out.exit_code == 0, out.output
    assert asked == [6, 12]


def test_every_command_tells_its_version():
    for module in ("snail_client", "snail_garbler", "snail_evaluator", "snail_bench.cli"):
        out = subprocess.run([sys.executable, "-m", module, "--version"], capture_output=True,
                             text=True, timeout=60)
        assert out.returncode == 0 and "version 0.1.0" in out.stdout, (module, out)


def test_quiet_keeps_only_results_and_verbose_adds_the_cost():
    quiet = CliRunner().invoke(client, ["-q", "localize", "--backend", "float64", "--input",
                                        N6])
    assert quiet.exit_code == 0 and quiet.stdout.startswith("rvec [")  # the result stays
    assert len(quiet.stdout.splitlines()) == 1 and "rms" not in quiet.stdout
    loud = CliRunner().invoke(client, ["-v", "localize", "--backend", "float64", "--input",
                                       N6])
    assert loud.exit_code == 0 and "rms" in loud.stdout and "secure runs" in loud.stderr
    both = CliRunner().invoke(client, ["-v", "-q", "localize", "--input", N6])
    assert both.exit_code == 2


def test_progress_bars_only_on_a_terminal(monkeypatch):
    from snail_client.progress import bar

    assert bar(3, "x").disable  # tests run with stderr captured: no terminal
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert not bar(3, "x").disable
    assert bar(3, "x", quiet=True).disable
