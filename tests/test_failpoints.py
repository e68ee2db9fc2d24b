"""Failpoints: $SNAIL_FAILPOINTS read at a daemon's start only, a no-op otherwise, loud
when armed (snail_common/failpoints.py)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from snail_client.blocking import SecureRunner
from snail_client.embedded import embedded_services
from snail_common import failpoints


@pytest.fixture
def disarmed():
    """Every test leaves this process's registry as it found it: empty."""
    yield
    failpoints.configure("garbler", {})


def test_nothing_fires_unless_armed(disarmed):
    failpoints.configure("garbler", {})
    assert failpoints.armed() == []
    assert not any(failpoints.fire(name) for name in failpoints.NAMES for _ in range(5))


@pytest.mark.parametrize(("when", "fires"), [
    ("always", [1, 2, 3, 4, 5, 6]),
    ("1/1", [1, 2, 3, 4, 5, 6]),
    ("1/3", [3, 6]),
    ("run:2", [2]),
])
def test_when_counts_the_passes_from_one(disarmed, when, fires):
    failpoints.configure("garbler", {failpoints.ENV: f"garbler.zero_label={when}"})
    assert failpoints.armed() == [f"garbler.zero_label={when}"]
    got = [k for k in range(1, 7) if failpoints.fire("garbler.zero_label")]
    assert got == fires
    assert not failpoints.fire("garbler.table_bit")  # not armed: its own count


def test_a_daemon_arms_its_own_role_only(disarmed):
    env = {failpoints.ENV: " garbler.table_bit=always ; evaluator.digest=1/2 ;"}
    assert failpoints.configure("evaluator", env) == ["evaluator.digest=1/2"]
    assert not failpoints.fire("garbler.table_bit")
    assert failpoints.configure("garbler", env) == ["garbler.table_bit=always"]


def test_the_compose_override_arms_a_cheat_of_the_garbler_alone(disarmed):
    """docker-compose.failpoints.yml (deploy/compose-test's cheating garbler): a typo there
    would show only where a Docker engine runs (the garbler exits 2); its point is the
    swapped zero-label, which leaves every label valid, so that the audit names the
    garbler (what deploy/compose-test expects), not the decoding."""
    path = Path(__file__).resolve().parent.parent / "docker-compose.failpoints.yml"
    services = yaml.safe_load(path.read_text())["services"]
    assert set(services) == {"garbler"}
    env = services["garbler"]["environment"]
    assert failpoints.configure("garbler", env) == ["garbler.zero_label=always"]
    assert failpoints.configure("evaluator", env) == []


@pytest.mark.parametrize(("value", "says"), [
    ("garbler.tabel_bit=always", "unknown failpoint 'garbler.tabel_bit'"),
    ("garbler.table_bit", "expected garbler.table_bit=always"),
    ("garbler.table_bit=sometimes", "expected"),
    ("garbler.table_bit=1/0", "expected"),
    ("garbler.table_bit=run:0", "expected"),
    ("garbler.table_bit=always;garbler.table_bit=run:1", "set twice"),
])
def test_a_bad_setting_names_itself(disarmed, value, says):
    with pytest.raises(failpoints.FailpointError, match="SNAIL_FAILPOINTS") as info:
        failpoints.configure("garbler", {failpoints.ENV: value})
    assert says in str(info.value)


@pytest.mark.parametrize("role", ["garbler", "evaluator"])
def test_a_daemon_with_a_bad_setting_exits_2_naming_it(tmp_path, role):
    args = ["--listen", "127.0.0.1:0", "--tls-dir", str(tmp_path)]
    if role == "garbler":
        args += ["--evaluator", "127.0.0.1:1"]
    done = subprocess.run([sys.executable, "-m", f"snail_{role}", *args],
                          env={"SNAIL_FAILPOINTS": "evaluator.label=always", "PATH": ""},
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert "$SNAIL_FAILPOINTS: unknown failpoint 'evaluator.label'" in done.stderr


def test_armed_daemons_warn_at_start_and_in_health(tmp_path):
    env = {failpoints.ENV: "garbler.zero_label=run:3;evaluator.digest=1/4",
           "SNAIL_CACHE_DIR": str(tmp_path)}
    with embedded_services(log_level="warning", env=env) as svc, SecureRunner(
            svc.garbler_addr, svc.evaluator_addr, svc.tls_dir) as runner:
        for daemon, armed in ((svc.garbler, "garbler.zero_label=run:3"),
                              (svc.evaluator, "evaluator.digest=1/4")):
            lines = [json.loads(x) for x in daemon.log.read_text().splitlines()]
            warned = [x for x in lines if x["event"] == "failpoints"]
            assert len(warned) == 1 and warned[0]["level"] == "warning"
            assert warned[0]["armed"] == [armed]
            assert runner.health(daemon.role)["failpoints"] == [armed]


def test_unarmed_daemons_say_nothing_of_failpoints(tmp_path):
    with embedded_services(log_level="info", env={"SNAIL_CACHE_DIR": str(tmp_path)}) as svc, \
            SecureRunner(svc.garbler_addr, svc.evaluator_addr, svc.tls_dir) as runner:
        assert "failpoints" not in runner.health("garbler")
        assert '"failpoints"' not in svc.garbler.log.read_text()
