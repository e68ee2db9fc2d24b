"""Embedded daemons end with the process that started them, even when it is SIGKILLed
(before, they lived on, holding their ports and memory)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

STARTER = """
import time
from snail_client.embedded import embedded_services

with embedded_services() as svc:
    print(svc.garbler.process.pid, svc.evaluator.process.pid, flush=True)
    time.sleep(600)
"""


def _running(pid: int) -> bool:
    """Alive and not a zombie (an orphan's zombie may wait for a reaper)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False
    return "\nState:\tZ" not in status


def _survivors(pids: list[int], seconds: float) -> list[int]:
    """Those of ``pids`` still running after ``seconds``, killed then (nothing is left)."""
    deadline = time.monotonic() + seconds
    while any(_running(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = [p for p in pids if _running(p)]
    for pid in alive:
        os.kill(pid, signal.SIGKILL)
    return alive


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_daemons_exit_when_their_starter_is_killed():
    starter = subprocess.Popen([sys.executable, "-c", STARTER], stdout=subprocess.PIPE,
                               text=True)
    try:
        pids = [int(p) for p in starter.stdout.readline().split()]
        assert len(pids) == 2 and all(_running(p) for p in pids)
    finally:
        starter.send_signal(signal.SIGKILL)
        starter.wait()
    assert not _survivors(pids, 20), "an embedded daemon outlived its SIGKILLed starter"


COMPILER = """
from snail_bench.paper import precompile, sil_spec

precompile([sil_spec("lm", 256)])  # a cold cache: compiling takes far longer than the test
"""


def _children(pid: int) -> list[int]:
    kids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(entry.name))
    return kids


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_circuit_compiling_for_the_paper_run_ends_with_the_run(tmp_path):
    """``snail-bench paper`` compiles each circuit in a child for minutes: a run killed
    mid-compile must not leave the compiler working (and holding gigabytes)."""
    env = {**os.environ, "SNAIL_CACHE_DIR": str(tmp_path)}
    starter = subprocess.Popen([sys.executable, "-c", COMPILER], env=env)
    try:
        deadline = time.monotonic() + 30
        while not (kids := _children(starter.pid)) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert kids, "the compiler child never started"
    finally:
        starter.send_signal(signal.SIGKILL)
        starter.wait()
    assert not _survivors(kids, 15), "the compiler outlived its SIGKILLed run"
