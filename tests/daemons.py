"""Embedded daemons started with particular flags, for tests of what the flags change."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from snail_client.embedded import Daemon, Services, embedded_services


def daemons_with(tmp_path_factory, *flags: str) -> Iterator[Services]:
    """Both daemons on loopback with ``flags``, sharing a fresh circuit cache."""
    cache = tmp_path_factory.mktemp("cache")
    with embedded_services(env={"SNAIL_CACHE_DIR": str(cache)}, extra_args=flags) as svc:
        yield svc


def start_patched_evaluator(script: str, log: Path, *flags: str) -> Daemon:
    """An evaluator run by ``script`` (which patches the daemon, then calls its main)
    listening on loopback with ``flags``: to make a race of the real service happen
    deterministically."""
    with open(log, "wb") as err:
        proc = subprocess.Popen(
            [sys.executable, "-c", script, "--listen", "127.0.0.1:0", "--log-level", "info",
             *flags],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        for line in log.read_text().splitlines():
            entry = json.loads(line)
            if entry.get("event") == "listening":
                return Daemon("evaluator", proc, f"127.0.0.1:{entry['port']}", log)
        assert proc.poll() is None, log.read_text()
        time.sleep(0.05)
    proc.kill()
    raise AssertionError(f"the evaluator did not start: {log.read_text()}")


def session_outcomes(log: Path) -> list[str]:
    """The outcome of every session line in a daemon's log, in order."""
    return [json.loads(line)["outcome"] for line in log.read_text().splitlines()
            if '"event": "session"' in line]


def session_lines(log: Path) -> list[dict]:
    """Every session line of a daemon's log, in the order the sessions ended."""
    return [json.loads(line) for line in log.read_text().splitlines()
            if '"event": "session"' in line]


def evaluator_runs(services: Services) -> list[dict]:
    """The evaluator's sessions that ran (outcome ok): one per secure run."""
    return [s for s in session_lines(services.evaluator.log) if s["outcome"] == "ok"]


def sigint_default() -> None:
    """``preexec_fn`` for a child that a test interrupts with SIGINT: it gets SIGINT as a
    terminal's Ctrl-C would reach it, also when this test run was started in the
    background by a non-interactive shell, which starts its jobs with SIGINT ignored (and
    children inherit that: Python then installs no KeyboardInterrupt handler)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
