"""What trusting no single server costs (``snail-bench audits``): the garbler's digest and
signature and the evaluator's digest and check, as a share of that server's CPU per run,
and the client's CPU per audited run and on average at the default audit rate.

Both daemons run on loopback; the servers' CPU is read from each daemon's process CPU
clock over a batch of runs (Linux: all its threads, exited ones too, in nanoseconds;
/proc's utime + stime count 10 ms ticks, 0.4 points of the share in a 30-run n = 6
batch), their digest and signature seconds from each run's stats (the threads' own CPU
clock around those calls). The client's audit (unaudited runs here: rate 0) is timed on
this process's CPU clock, the schedule already loaded (the first audit of a circuit
also loads or compiles its schedule: ``schedule_load_s``, wall).

Runs are half-gates (the scheme the audit garbles again), so the stream is exactly
``stream_bytes``; each server's ``digest_gb_per_s`` is that over its hashing seconds, to
compare with ``digest_in_cache_gb_per_s``, the same hash in this process over one frame
already in cache: the rate the digest cannot beat here, so its floor share.
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from snail_client.audit import DEFAULT_AUDIT_RATE
from snail_client.blocking import SecureRunner
from snail_client.embedded import embedded_services
from snail_client.evidence import regarble
from snail_common.circuit import registry
from snail_common.gc import fresh_delta, fresh_seed
from snail_common.gc.attest import TableDigest
from snail_common.gc.engine import resolve
from snail_common.gc.stream import BYTES_PER_AND, HEADER, SCHEME_HALF_GATES
from snail_common.pnp.spec import Spec
from snail_garbler.daemon import frame_plan

from .choices import link_args

_CPUCLOCK_SCHED = 2  # Linux: a process CPU clock id is (~pid << 3) | CPUCLOCK_SCHED
_IN_CACHE_PASSES = 50
# each server's stats: its hashing seconds, then its signature (or check) seconds
_ATTEST_KEYS = {"garbler": ("garbler_digest_s", "garbler_sign_s"),
                "evaluator": ("evaluator_digest_s", "evaluator_verify_s")}
_ROLES = tuple(_ATTEST_KEYS)


def _cpu_s(pid: int) -> float:
    """CPU seconds process ``pid`` has used so far, all its threads (its CPU clock)."""
    return time.clock_gettime((~pid << 3) | _CPUCLOCK_SCHED)


def _spread(values: list[float]) -> dict[str, float]:
    return {"median": round(statistics.median(values), 6), "min": round(min(values), 6),
            "max": round(max(values), 6)}


def audit_report(specs: list[Spec], repeat: int, batches: int, audits: int,
                 table_link: str | None = None) -> dict:
    """Per circuit: the servers' attestation shares and the client's audit costs, with
    the daemons' ``--table-link`` (None: their default; the report names the one used)."""
    out: dict[str, dict] = {}
    with embedded_services(extra_args=link_args(table_link)) as svc, SecureRunner(
            svc.garbler_addr, svc.evaluator_addr, svc.tls_dir, scheme="halfgates",
            audit_rate=0.0) as runner:
        pids = {"garbler": svc.garbler.process.pid, "evaluator": svc.evaluator.process.pid}
        for spec in specs:
            out[spec.registry_id] = _measure(runner, spec, pids, repeat, batches, audits)
        link = runner.health("evaluator").get("table_link", "tls")
    return {"audits": out, "table_link": link}


def _in_cache_rate(frame_bytes: int) -> float:
    """GB/s of TableDigest over one frame of ``frame_bytes`` hashed again and again (in
    this core's cache), on this thread's CPU clock: the median pass."""
    frame = memoryview(np.random.default_rng(0).bytes(frame_bytes))
    passes = []
    for _ in range(_IN_CACHE_PASSES):
        digest = TableDigest()
        t0 = time.thread_time()
        digest.update(frame)
        digest.digest()
        passes.append(time.thread_time() - t0)
    return frame_bytes / statistics.median(passes) / 1e9


def _measure(runner: SecureRunner, spec: Spec, pids: dict[str, int], repeat: int,
             batches: int, audits: int) -> dict:
    circuit_id = spec.registry_id
    rng = np.random.default_rng(0)
    n_inputs = registry.interface(circuit_id).n_inputs

    def run() -> dict[str, float]:
        return runner.invoke(circuit_id, rng.random(n_inputs) < 0.5).timing

    run()  # loads the circuit on both servers
    n_and = registry.interface(circuit_id).counts["and"]
    stream_bytes = HEADER.size + BYTES_PER_AND[SCHEME_HALF_GATES] * n_and
    shares: dict[str, list[float]] = {role: [] for role in _ROLES}
    own: dict[str, list[float]] = {role: [] for role in _ROLES}
    rates: dict[str, list[float]] = {role: [] for role in _ROLES}
    server_cpu: dict[str, list[float]] = {role: [] for role in _ROLES}
    client_cpu: list[float] = []
    for _ in range(batches):
        before = {role: _cpu_s(pid) for role, pid in pids.items()}
        c0 = time.process_time()
        hashing = dict.fromkeys(_ROLES, 0.0)
        signing = dict.fromkeys(_ROLES, 0.0)
        for _ in range(repeat):
            timing = run()
            for role, (digest_key, sign_key) in _ATTEST_KEYS.items():
                hashing[role] += timing[digest_key]
                signing[role] += timing[sign_key]
        client_cpu.append((time.process_time() - c0) / repeat)
        for role, pid in pids.items():
            cpu = _cpu_s(pid) - before[role]
            spent = hashing[role] + signing[role]
            server_cpu[role].append(cpu / repeat)
            own[role].append(spent / repeat)
            shares[role].append(spent / cpu if cpu > 0 else float("nan"))
            rates[role].append(stream_bytes * repeat / hashing[role] / 1e9 if hashing[role] > 0
                               else float("nan"))
    t0 = time.perf_counter()
    _, schedule = registry.compiled(circuit_id)  # what the client's first audit loads
    first_audit_s = time.perf_counter() - t0
    block, frame_bytes = frame_plan(schedule, SCHEME_HALF_GATES, resolve())  # the garbler's
    audit_cpu = []
    for _ in range(audits):
        c0 = time.process_time()
        regarble(circuit_id, fresh_seed(), fresh_delta(), bytes(16), "halfgates", block)
        audit_cpu.append(time.process_time() - c0)
    base, audit = statistics.median(client_cpu), statistics.median(audit_cpu)
    return {
        "points": spec.points, "and": n_and, "runs": repeat * batches, "engine": resolve(),
        "stream_bytes": stream_bytes,
        "digest_in_cache_gb_per_s": round(_in_cache_rate(frame_bytes), 3),
        **{role: {"attest_share": _spread(shares[role]),
                  "attest_s_per_run": _spread(own[role]),
                  "cpu_s_per_run": _spread(server_cpu[role]),
                  "digest_gb_per_s": _spread(rates[role])} for role in _ROLES},
        "client": {"cpu_s_per_run_unaudited": _spread(client_cpu),
                   "cpu_s_per_audit": _spread(audit_cpu),
                   "schedule_load_s": round(first_audit_s, 4),
                   "default_rate": DEFAULT_AUDIT_RATE,
                   "cpu_s_per_run_at_default_rate": round(base + DEFAULT_AUDIT_RATE * audit, 6),
                   "overhead_at_default_rate": round(DEFAULT_AUDIT_RATE * audit / base, 4)},
    }
