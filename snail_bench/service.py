"""End-to-end pace of secure invocations (``snail-bench service``).

What a user waits for: the wall time of one secure run of a localization circuit, client
to both servers and back over TLS, plus the bytes on each link. Inputs are fresh random
bits: garbling does the same work whatever the data. The first run of each circuit is
reported apart (``first_s``), since a freshly started daemon also loads the circuit then.
With the embedded daemons the servers' peak RSS is read from /proc (Linux).
"""

from __future__ import annotations

import secrets
import statistics
from pathlib import Path

import numpy as np

from snail_client.embedded import connected
from snail_client.secure import Invocation, SecureRunner
from snail_common.circuit import registry
from snail_common.pnp.spec import Spec


def service_report(specs: list[Spec], repeat: int, garbler: str | None = None,
                   evaluator: str | None = None, tls_dir: str | None = None) -> dict:
    """``{"service": {circuit_id: {...}}}``: per circuit, the first run and ``repeat``
    warm runs (median, min, max wall seconds), bytes per link and server timings of one
    run, and (embedded daemons only) each server's peak RSS so far: a high-water mark
    over the daemon's life, so with several circuits it covers the largest run yet."""
    report: dict[str, dict] = {}
    with connected(garbler, evaluator, tls_dir) as (runner, services):
        for spec in specs:
            report[spec.circuit_id] = _measure(runner, spec, repeat)
            if services is not None:
                report[spec.circuit_id]["peak_rss_mb"] = {
                    daemon.role: _peak_rss_mb(daemon.process.pid)
                    for daemon in (services.garbler, services.evaluator)}
    return {"service": report}


def _measure(runner: SecureRunner, spec: Spec, repeat: int) -> dict:
    iface = registry.interface(spec.registry_id)
    rng = np.random.default_rng(secrets.randbits(128))

    def once() -> Invocation:
        return runner.invoke(spec.registry_id, rng.integers(0, 2, iface.n_inputs).astype(bool))

    first = once()
    runner.expect(spec.registry_id, repeat)  # garble ahead, as a padded frame does
    warm = [once() for _ in range(repeat)]
    walls = [run.wall_s for run in warm]
    return {"and": iface.counts["and"], "depth": iface.depth, "first_s": round(first.wall_s, 4),
            "median_s": round(statistics.median(walls), 4), "min_s": round(min(walls), 4),
            "max_s": round(max(walls), 4), "repeat": repeat, "traffic": warm[-1].traffic,
            "timing": {k: round(v, 4) for k, v in warm[-1].timing.items()}}


def _peak_rss_mb(pid: int) -> float | None:
    """VmHWM of a live process in MB, or None where /proc does not have it."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        pass
    return None
