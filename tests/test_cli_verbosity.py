"""-v/-q as users type them: before or after the subcommand, on every command of every
entry point, and -q still prints the result (FORMATS: "Every command: -v/-q, --version")."""

from __future__ import annotations

import json

import click
import pytest
from click.testing import CliRunner
from shared_paths import EXAMPLES

from snail_bench.cli import main as bench_main
from snail_client.cli import main as client_main
from snail_demo.cli import main as demo_main
from snail_evaluator.cli import main as evaluator_main
from snail_garbler.cli import main as garbler_main
from snail_mapd.cli import main as mapd_main

GROUPS = {"snail-client": client_main, "snail-bench": bench_main, "snail-demo": demo_main}
DAEMONS = {"snail-garbler": garbler_main, "snail-evaluator": evaluator_main,
           "snail-mapd": mapd_main}
SUBCOMMANDS = [(prog, name) for prog, group in GROUPS.items() for name in group.commands]
N6 = str(EXAMPLES / "synthetic_n6.json")


def _run(command: click.Command, args: list[str]):
    return CliRunner().invoke(command, args, catch_exceptions=False)


@pytest.mark.parametrize("flag", ["-v", "-q", "--verbose", "--quiet", "--version"])
@pytest.mark.parametrize(("prog", "name"), SUBCOMMANDS)
def test_every_subcommand_takes_the_flags_after_its_name(prog: str, name: str, flag: str):
    # --help is eager: a flag the subcommand does not know fails parsing before it.
    result = _run(GROUPS[prog], [name, flag, "--help"])
    assert result.exit_code == 0, f"{prog} {name} {flag}: {result.output}"
    assert "No such option" not in result.output


@pytest.mark.parametrize("prog", sorted(DAEMONS))
def test_every_daemon_takes_the_flags(prog: str):
    for flag in ("-v", "-q", "--version"):
        result = _run(DAEMONS[prog], [flag, "--help"])
        assert result.exit_code == 0, f"{prog} {flag}: {result.output}"


@pytest.mark.parametrize("prog", sorted(GROUPS))
def test_version_after_the_subcommand(prog: str):
    group = GROUPS[prog]
    result = _run(group, [next(iter(group.commands)), "--version"])
    assert result.exit_code == 0
    assert result.stdout.startswith(f"{prog}, version ")


@pytest.mark.parametrize("args", [
    ["localize", "--input", N6, "--backend", "float64", "-q"],
    ["-q", "localize", "--input", N6, "--backend", "float64"],
    ["localize", "-q", "--input", N6, "--backend", "float64"],
])
def test_quiet_still_prints_the_result(args: list[str]):
    result = _run(client_main, args)
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("rvec [") and "tvec [" in lines[0]
    assert lines[0].endswith("converged")
    # the same pose as the full record
    record = json.loads(_run(client_main, ["localize", "--input", N6, "--backend", "float64",
                                           "--json"]).stdout)
    rvec = json.loads(lines[0].split("rvec ")[1].split("  tvec")[0])
    assert rvec == pytest.approx(record["rvec"], abs=1e-6)


def test_quiet_track_prints_one_line_a_frame(tmp_path):
    (tmp_path / "a.json").write_text((EXAMPLES / "synthetic_n6.json").read_text())
    (tmp_path / "b.json").write_text((EXAMPLES / "synthetic_n6.json").read_text())
    result = _run(client_main, ["track", "--input", str(tmp_path), "--backend", "float64",
                                "-q"])
    assert result.exit_code == 0, result.output
    assert len(result.stdout.splitlines()) == 2
    assert all(line.startswith("rvec [") for line in result.stdout.splitlines())


def test_quiet_json_is_still_json():
    result = _run(client_main, ["localize", "--input", N6, "--backend", "float64", "--json",
                                "-q"])
    assert json.loads(result.stdout)["status"] == "converged"


def test_verbose_after_the_subcommand_reports_on_stderr():
    result = _run(client_main, ["localize", "--input", N6, "--backend", "float64", "-v"])
    assert result.exit_code == 0
    assert "secure runs" in result.stderr
    assert result.stdout.startswith("rvec [")


@pytest.mark.parametrize("args", [
    ["localize", "--input", N6, "--backend", "float64", "-v", "-q"],
    ["-v", "localize", "--input", N6, "--backend", "float64", "-q"],
    ["-q", "localize", "--input", N6, "--backend", "float64", "-v"],
])
def test_verbose_and_quiet_together_is_a_usage_error(args: list[str]):
    result = _run(client_main, args)
    assert result.exit_code == 2
    assert "-v and -q: choose one" in result.stderr
