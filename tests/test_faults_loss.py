"""Packet loss of 5 % and 30 % on each link of the network lab (real namespaces, a
packet forwarder that drops): a localization either completes equal to the cleartext
circuit's or fails with one clear line, within a stated bound; the daemons then serve a
clean run. Needs root (CI is); skipped with the reason otherwise."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest
from shared_paths import EXAMPLES

from snail_bench.netlab.namespaces import LINKS, Lab, LabUnavailable, Shape, check_capable
from snail_bench.netlab.services import lab_services

EXAMPLE = EXAMPLES / "synthetic_n6.json"
BOUND_S = 240.0  # per localization: a 30 % loss link may take minutes, never longer
LINK_TIMEOUT = 30


def _unavailable() -> str | None:
    try:
        check_capable()
    except (LabUnavailable, Exception) as exc:
        return f"network lab unavailable: {exc}"
    return None


REASON = _unavailable()
pytestmark = pytest.mark.skipif(REASON is not None, reason=REASON or "")


def _localize(*args: str, prefix: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    return subprocess.run([*prefix, sys.executable, "-m", "snail_client", "localize",
                           "--input", str(EXAMPLE), "--min-invocations", "1", "--json",
                           "--link-timeout", str(LINK_TIMEOUT), *args],
                          capture_output=True, text=True, timeout=BOUND_S)  # a hang guard


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    with Lab() as lab, lab_services(lab, tmp_path_factory.mktemp("loss")) as services:
        yield lab, services
    assert lab.leftovers() == []


@pytest.fixture(scope="module")
def clear():
    proc = _localize("--backend", "cleartext")
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


@pytest.mark.parametrize("loss", [5, 30])
@pytest.mark.parametrize("link", list(LINKS))
def test_a_lossy_link_gives_the_right_pose_or_one_clear_error(lab, clear, link, loss):
    lab, services = lab
    lab.shape({link: Shape(loss_pct=loss)})
    try:
        t0 = time.monotonic()
        proc = _localize(*services.client_args(), prefix=lab.exec_prefix("client"))
        took = time.monotonic() - t0
    finally:
        lab.shape({link: Shape()})
    print(f"{link} {loss} % loss: exit {proc.returncode} after {took:.1f} s "
          f"{proc.stderr.strip()[-300:]}")
    if proc.returncode == 0:
        garbled = json.loads(proc.stdout)
        for key in ("rvec", "tvec", "iterations", "cost", "status"):
            assert garbled[key] == clear[key], key
    else:
        assert loss >= 30, proc.stderr  # 5 % loss is ordinary WiFi: it must complete
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 1 and len(lines) == 1 and "Traceback" not in proc.stderr
    after = _localize(*services.client_args(), prefix=lab.exec_prefix("client"))
    assert after.returncode == 0, after.stderr
    assert json.loads(after.stdout)["rvec"] == clear["rvec"]
