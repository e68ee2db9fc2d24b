"""Hold a fleet of clients against one daemon pair for minutes (``snail-bench soak``).

What an operator needs before leaving the service up for days: does it stay correct, does
it keep serving, and does it leak. One garbler and evaluator pair runs on loopback (real
daemon processes, mutual TLS); C client *processes*, each with its own certificate (as
separate devices would have), localize random synthetic scenes in a loop with mixed point
counts and algorithms, every frame padded to ``min_invocations`` secure runs as the
privacy policy asks. Each frame's pose is checked here against the cleartext backend on
the same scene (regenerated from its seed): garbled and cleartext must agree bit for bit.

Meanwhile each daemon's RSS (``/proc/PID/status`` VmRSS) and open file descriptors
(``/proc/PID/fd``) are sampled every few seconds. ``soak_report.py`` turns what the
clients and the sampler saw into the report.
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing as mp
import os
import queue
import secrets
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from snail_client.blocking import SecureRunner
from snail_client.embedded import embedded_services
from snail_client.links import ServiceError
from snail_client.progress import bar
from snail_common.circuit import registry
from snail_common.net.tls import add_client

from .soak_report import EXAMPLES_KEPT, ROLES, Plan, Sample, Tally, daemon_log, summarize

IDLE_LIMIT_S = 40.0  # beyond the daemons' 30 s session timeout
COMPARED = ("rvec", "tvec", "cost", "iterations", "status")


# ---- the client processes ---------------------------------------------------------------

@dataclass(frozen=True)
class ClientJob:
    """What a client process needs: where the servers are, who it is, what to run."""

    index: int
    garbler: str
    evaluator: str
    tls_dir: str
    cert_name: str
    plan: Plan
    start: float  # time.monotonic() of the soak's start (one clock for all processes)


def failure_kind(exc: BaseException) -> str:
    """The error kind a failure counts under: the server's code when one refused or
    failed the session, else what the client saw."""
    if isinstance(exc, ServiceError):
        if exc.code:
            return exc.code
        text = str(exc)
        if "integrity" in text:
            return "integrity"
        if "no result within" in text:
            return "client_timeout"
        return "connection"
    return f"client_{type(exc).__name__}"


def client_main(job: ClientJob, out: mp.Queue) -> None:
    """Localize random scenes until the soak's end; report each invocation, each frame
    (with its scene seed, for the cleartext check) and each failure on ``out``."""
    from snail_common import families

    families.register_all()
    from snail_client.localize import Options, backend_for, localize
    from snail_common.loc.synthetic import random_scene

    plan = job.plan
    rng = np.random.default_rng(secrets.randbits(128))
    base = Options(backend="garbled", garbler=job.garbler, evaluator=job.evaluator,
                   tls_dir=job.tls_dir, cert_name=job.cert_name,
                   min_invocations=plan.min_invocations)
    end = job.start + plan.minutes * 60
    try:
        with backend_for(base) as backend:
            def invoked() -> None:
                last = backend.secure.last
                latency = last.wall_s + last.timing.get("client_busy_wait_s", 0.0)
                out.put(("inv", time.monotonic() - job.start, latency))

            backend.on_invocation = invoked
            while time.monotonic() < end:
                n = int(rng.choice(plan.points))
                algorithm = str(rng.choice(plan.algorithms))
                seed = int(rng.integers(2**63))
                problem = random_scene(np.random.default_rng(seed), n)
                options = dataclasses.replace(base, algorithm=algorithm)
                try:
                    result = localize(problem, options, backend)
                except Exception as exc:  # every failure is counted, none ends the soak
                    out.put(("fail", time.monotonic() - job.start, failure_kind(exc),
                             f"client {job.index}: {exc}"))
                    continue
                out.put(("frame", job.index, seed, n, algorithm,
                         {k: result[k] for k in COMPARED}))
    except Exception as exc:  # e.g. the first connection failed
        out.put(("fail", time.monotonic() - job.start, failure_kind(exc),
                 f"client {job.index}: {exc}"))
    finally:
        out.put(("done", job.index))


def check_frame(seed: int, n: int, algorithm: str, garbled: dict,
                min_invocations: int) -> dict | None:
    """None when the cleartext backend gives the garbled frame's pose bit for bit on the
    same scene, else what differs."""
    from snail_client.localize import Options, localize
    from snail_common.loc.backends import CircuitBackend
    from snail_common.loc.synthetic import random_scene

    problem = random_scene(np.random.default_rng(seed), n)
    clear = localize(problem, Options(backend="cleartext", algorithm=algorithm,
                                      min_invocations=min_invocations), CircuitBackend())
    differ = [k for k in COMPARED if clear[k] != garbled[k]]
    if not differ:
        return None
    return {"seed": seed, "points": n, "algorithm": algorithm,
            "fields": {k: {"garbled": garbled[k], "cleartext": clear[k]} for k in differ}}


# ---- the daemons' footprint -------------------------------------------------------------

def footprint(pid: int) -> tuple[float, int] | None:
    """(RSS in MB, open file descriptors) of a live process, None once it is gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return None
    for line in status.splitlines():
        if line.startswith("VmRSS:"):
            return round(int(line.split()[1]) / 1024, 1), fds
    return None


def _health(monitor: SecureRunner, role: str) -> tuple[int | None, float | None]:
    """(sessions under way, MB buffered ahead) from a daemon's health message."""
    try:
        sessions = monitor.health(role)["sessions"]
    except ServiceError:
        return None, None
    return int(sessions["active"]), round(sessions["queued_bytes"] / 2**20, 1)


def _sampler(pids: dict[str, int], monitor: SecureRunner, start: float, every: float,
             tally: Tally, stop: threading.Event) -> None:
    while True:
        now = time.monotonic() - start
        for role, pid in pids.items():
            seen = footprint(pid)
            if seen is not None:
                tally.samples.append(Sample(now, role, *seen, *_health(monitor, role)))
        if stop.wait(every):
            return


def _until_idle(monitor: SecureRunner, pids: dict[str, int], limit: float) -> dict:
    """Once every client is gone: wait (up to ``limit`` seconds) until no session is under
    way and nothing is buffered, and report each daemon's state then (with its RSS and
    fds). A session still held after its clients left would be a leak."""
    t0 = time.monotonic()
    while True:
        state = {role: dict(zip(("sessions", "queued_mb"), _health(monitor, role)))
                 for role in ROLES}
        idle = all(v["sessions"] == 0 and v["queued_mb"] == 0 for v in state.values())
        if idle or time.monotonic() - t0 > limit:
            for role, pid in pids.items():
                state[role].update(zip(("rss_mb", "fds"), footprint(pid) or (None, None)))
            return {"idle": idle, "seconds": round(time.monotonic() - t0, 1), **state}
        time.sleep(0.5)


# ---- the run ----------------------------------------------------------------------------

def _warm_up(garbler: str, evaluator: str, tls_dir: str, plan: Plan) -> None:
    """One run of every circuit before the clock starts: the daemons load (or compile)
    them then, which is start-up, not soak."""
    from snail_common.loc.pipeline import Options

    ids = {Options(algorithm=a, min_invocations=plan.min_invocations).spec(n).registry_id
           for a in plan.algorithms for n in plan.points}
    with SecureRunner(garbler, evaluator, tls_dir) as runner:
        for circuit_id in sorted(ids):
            bits = np.frombuffer(os.urandom(registry.interface(circuit_id).n_inputs),
                                 np.uint8) & 1
            runner.run(circuit_id, bits.astype(bool))


def _absorb(message: tuple, tally: Tally, plan: Plan) -> None:
    kind = message[0]
    if kind == "inv":
        tally.invocations.append((message[1], message[2]))
    elif kind == "frame":
        _, index, seed, n, algorithm, garbled = message
        tally.frames += 1
        wrong = check_frame(seed, n, algorithm, garbled, plan.min_invocations)
        if wrong is not None:
            tally.wrong.append({"client": index, **wrong})
    elif kind == "fail":
        tally.failures[message[2]] += 1
        if len(tally.failure_examples) < EXAMPLES_KEPT:
            tally.failure_examples.append(message[3])


def run_soak(plan: Plan, quiet: bool = True, keep_logs: Path | None = None) -> dict:
    """Run the soak and return its ``{"soak": {...}}`` report (see ``soak_report``); with
    ``keep_logs``, the daemons' JSON logs are copied there (ROLE.log) for a post-mortem."""
    tally = Tally()
    ctx = mp.get_context("spawn")  # fresh interpreters: nothing shared with this one
    out: mp.Queue = ctx.Queue()
    with embedded_services(log_level="info") as services:
        tls_dir = str(services.tls_dir)
        garbler, evaluator = services.garbler_addr, services.evaluator_addr
        for name in (*(f"soak-{i:03d}" for i in range(plan.clients)), "soak-monitor"):
            add_client(tls_dir, name)
        _warm_up(garbler, evaluator, tls_dir, plan)
        pids = {d.role: d.process.pid for d in (services.garbler, services.evaluator)}
        monitor = SecureRunner(garbler, evaluator, tls_dir, cert_name="soak-monitor")
        try:
            elapsed = _fleet(plan, ctx, out, pids, monitor, tally, quiet,
                             ClientJob(0, garbler, evaluator, tls_dir, "", plan, 0.0))
            after = _until_idle(monitor, pids, IDLE_LIMIT_S)
        finally:
            monitor.close()
        logs = {d.role: daemon_log(d.log) for d in (services.garbler, services.evaluator)}
        if keep_logs is not None:
            keep_logs.mkdir(parents=True, exist_ok=True)
            for d in (services.garbler, services.evaluator):
                shutil.copyfile(d.log, keep_logs / f"{d.role}.log")
    report = summarize(tally, plan, elapsed)
    report["soak"]["daemon_logs"] = logs
    report["soak"]["after_clients_left"] = after
    return report


def _fleet(plan: Plan, ctx, out: mp.Queue, pids: dict[str, int], monitor: SecureRunner,
           tally: Tally, quiet: bool, template: ClientJob) -> float:
    """Start the sampler and the client processes, take their reports until all are
    done; returns the seconds from the start to the last client's end."""
    start = time.monotonic()
    stop = threading.Event()
    sampler = threading.Thread(target=_sampler, args=(
        pids, monitor, start, plan.sample_s, tally, stop), daemon=True)
    sampler.start()
    procs = [ctx.Process(target=client_main, daemon=True, args=(dataclasses.replace(
        template, index=i, cert_name=f"soak-{i:03d}", start=start), out))
        for i in range(plan.clients)]
    try:
        for proc in procs:
            proc.start()
        _collect(procs, out, tally, plan, start, quiet)
        return time.monotonic() - start
    finally:
        stop.set()
        sampler.join()
        for proc in procs:
            if proc.is_alive():
                proc.terminate()
            proc.join(10)


def _collect(procs: list, out: mp.Queue, tally: Tally, plan: Plan, start: float,
             quiet: bool) -> None:
    """Take the clients' messages (checking frames as they come) until every client said
    done or died; a client process that dies without a word is a failure."""
    done: set[int] = set()
    seconds = round(plan.minutes * 60)
    with bar(seconds, "soak", quiet, "s") as progress:
        while len(done) < len(procs):
            with contextlib.suppress(queue.Empty):
                message = out.get(timeout=0.5)
                if message[0] == "done":
                    done.add(message[1])
                else:
                    _absorb(message, tally, plan)
            progress.n = min(seconds, round(time.monotonic() - start))
            progress.refresh()
            for i, proc in enumerate(procs):
                if i not in done and proc.exitcode is not None and out.empty():
                    done.add(i)
                    tally.failures["client_died"] += 1
                    tally.failure_examples.append(f"client {i} exited with {proc.exitcode}")
