"""What trusting no single server costs (``snail-bench audits``): the garbler's digest and
signature and the evaluator's digest and check, as a share of that server's CPU per run,
and the client's CPU per audited run and on average at the default audit rate.

Both daemons run on loopback; the servers' CPU is read from /proc (Linux: utime + stime
of the daemon process over a batch of runs, all its threads), their digest and signature
seconds from each run's stats (the threads' own CPU clock around those calls). The
client's audit (unaudited runs here: rate 0) is timed on this process's CPU clock, the
schedule already loaded (the first audit of a circuit also loads or compiles its
schedule: ``schedule_load_s``, wall).
"""

from __future__ import annotations

import os
import statistics
import time
from pathlib import Path

import numpy as np

from snail_client.audit import DEFAULT_AUDIT_RATE
from snail_client.blocking import SecureRunner
from snail_client.embedded import embedded_services
from snail_client.evidence import regarble
from snail_common.circuit import registry
from snail_common.gc import fresh_delta, fresh_seed
from snail_common.gc.engine import resolve
from snail_common.gc.stream import SCHEME_HALF_GATES
from snail_common.pnp.spec import Spec
from snail_garbler.daemon import frame_plan

_TICK = os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (/proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _TICK


def _spread(values: list[float]) -> dict[str, float]:
    return {"median": round(statistics.median(values), 6), "min": round(min(values), 6),
            "max": round(max(values), 6)}


def audit_report(specs: list[Spec], repeat: int, batches: int, audits: int) -> dict:
    """Per circuit: the servers' attestation shares and the client's audit costs."""
    out: dict[str, dict] = {}
    with embedded_services() as svc, SecureRunner(svc.garbler_addr, svc.evaluator_addr,
                                                  svc.tls_dir, audit_rate=0.0) as runner:
        pids = {"garbler": svc.garbler.process.pid, "evaluator": svc.evaluator.process.pid}
        for spec in specs:
            out[spec.registry_id] = _measure(runner, spec, pids, repeat, batches, audits)
    return {"audits": out}


def _measure(runner: SecureRunner, spec: Spec, pids: dict[str, int], repeat: int,
             batches: int, audits: int) -> dict:
    circuit_id = spec.registry_id
    rng = np.random.default_rng(0)
    n_inputs = registry.interface(circuit_id).n_inputs

    def run() -> dict[str, float]:
        return runner.invoke(circuit_id, rng.random(n_inputs) < 0.5).timing

    run()  # loads the circuit on both servers
    shares: dict[str, list[float]] = {"garbler": [], "evaluator": []}
    own: dict[str, list[float]] = {"garbler": [], "evaluator": []}
    server_cpu: dict[str, list[float]] = {"garbler": [], "evaluator": []}
    client_cpu: list[float] = []
    for _ in range(batches):
        before = {role: _cpu_s(pid) for role, pid in pids.items()}
        c0 = time.process_time()
        spent = {"garbler": 0.0, "evaluator": 0.0}
        for _ in range(repeat):
            timing = run()
            spent["garbler"] += timing["garbler_digest_s"] + timing["garbler_sign_s"]
            spent["evaluator"] += timing["evaluator_digest_s"] + timing["evaluator_verify_s"]
        client_cpu.append((time.process_time() - c0) / repeat)
        for role, pid in pids.items():
            cpu = _cpu_s(pid) - before[role]
            server_cpu[role].append(cpu / repeat)
            own[role].append(spent[role] / repeat)
            shares[role].append(spent[role] / cpu if cpu > 0 else float("nan"))
    t0 = time.perf_counter()
    _, schedule = registry.compiled(circuit_id)  # what the client's first audit loads
    first_audit_s = time.perf_counter() - t0
    block, _ = frame_plan(schedule, SCHEME_HALF_GATES, resolve())  # as the garbler's
    audit_cpu = []
    for _ in range(audits):
        c0 = time.process_time()
        regarble(circuit_id, fresh_seed(), fresh_delta(), bytes(16), "halfgates", block)
        audit_cpu.append(time.process_time() - c0)
    base, audit = statistics.median(client_cpu), statistics.median(audit_cpu)
    return {
        "points": spec.points, "and": registry.interface(circuit_id).counts["and"],
        "runs": repeat * batches, "engine": resolve(),
        "garbler": {"attest_share": _spread(shares["garbler"]),
                    "attest_s_per_run": _spread(own["garbler"]),
                    "cpu_s_per_run": _spread(server_cpu["garbler"])},
        "evaluator": {"attest_share": _spread(shares["evaluator"]),
                      "attest_s_per_run": _spread(own["evaluator"]),
                      "cpu_s_per_run": _spread(server_cpu["evaluator"])},
        "client": {"cpu_s_per_run_unaudited": _spread(client_cpu),
                   "cpu_s_per_audit": _spread(audit_cpu),
                   "schedule_load_s": round(first_audit_s, 4),
                   "default_rate": DEFAULT_AUDIT_RATE,
                   "cpu_s_per_run_at_default_rate": round(base + DEFAULT_AUDIT_RATE * audit, 6),
                   "overhead_at_default_rate": round(DEFAULT_AUDIT_RATE * audit / base, 4)},
    }
