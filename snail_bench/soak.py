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

import asyncio
import dataclasses
import math
import multiprocessing as mp
import os
import secrets
import shutil
import threading
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from pathlib import Path

import numpy as np

from snail_client.blocking import SecureRunner
from snail_client.embedded import embedded_services
from snail_client.links import ServiceError
from snail_client.progress import bar
from snail_common.circuit import registry
from snail_common.gc.stream import SCHEMES
from snail_common.net.tls import add_client

from .soak_report import (
    EXAMPLES_KEPT,
    ROLES,
    Plan,
    Sample,
    Tally,
    daemon_log,
    summarize,
    within,
)

IDLE_LIMIT_S = 40.0  # beyond the daemons' 30 s session timeout
WARM_AT_ONCE = 4  # runs of each circuit at once in the warm-up
SETTLED_S = 6.0  # fds unchanged this long: at rest (the garbler's pooled links last 5 s)
SETTLE_LIMIT_S = 30.0
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


def client_main(job: ClientJob, out: Connection) -> None:
    """Localize random scenes until the soak's end; report each invocation, each frame
    (with its scene seed, for the cleartext check) and each failure on ``out`` (this
    client's own pipe: a client killed mid-message garbles nobody else's)."""
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
                out.send(("inv", time.monotonic() - job.start, latency))

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
                    out.send(("fail", time.monotonic() - job.start, failure_kind(exc),
                              f"client {job.index}: {exc}"))
                    continue
                out.send(("frame", job.index, seed, n, algorithm,
                          {k: result[k] for k in COMPARED}))
    except Exception as exc:  # e.g. the first connection failed
        out.send(("fail", time.monotonic() - job.start, failure_kind(exc),
                  f"client {job.index}: {exc}"))
    finally:
        out.send(("done", job.index))
        out.close()


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


def _state(monitor: SecureRunner, pids: dict[str, int]) -> dict:
    """Each daemon's sessions, tables buffered ahead, RSS and open fds now."""
    state = {role: dict(zip(("sessions", "queued_mb"), _health(monitor, role)))
             for role in ROLES}
    for role, pid in pids.items():
        state[role].update(zip(("rss_mb", "fds"), footprint(pid) or (None, None)))
    return state


def _idle_before(monitor: SecureRunner, pids: dict[str, int]) -> dict:
    """The daemons' footprint at rest before the fleet: once the warm-up's sessions are
    over and their pooled links have gone (their fds unchanged for a while)."""
    t0, last, since = time.monotonic(), None, time.monotonic()
    while time.monotonic() - t0 < SETTLE_LIMIT_S:
        state = _state(monitor, pids)
        fds = tuple(state[role]["fds"] for role in ROLES)
        if fds != last:
            last, since = fds, time.monotonic()
        elif time.monotonic() - since >= SETTLED_S and all(
                state[role]["sessions"] == 0 for role in ROLES):
            break
        time.sleep(0.5)
    return {role: {k: state[role][k] for k in ("fds", "rss_mb")} for role in ROLES}


def _until_idle(monitor: SecureRunner, pids: dict[str, int], before: dict,
                limit: float) -> dict:
    """Once every client is gone: wait (up to ``limit`` seconds) until no session is under
    way, nothing is buffered and each daemon's fds and RSS are back within 10 % of
    ``before`` (an idle daemon sweeps its memory a moment after its last session and
    connection end), and report each daemon's state then. A session, descriptor or
    buffer still held after its clients left would be a leak."""
    t0 = time.monotonic()
    while True:
        state = _state(monitor, pids)
        idle = all(v["sessions"] == 0 and v["queued_mb"] == 0 for v in state.values())
        back = {what: all(state[role][what] is not None and within(
            state[role][what], before[role][what]) for role in ROLES)
            for what in ("fds", "rss_mb")}
        if (idle and all(back.values())) or time.monotonic() - t0 > limit:
            return {"idle": idle, "fds_back": back["fds"], "rss_back": back["rss_mb"],
                    "seconds": round(time.monotonic() - t0, 1), **state}
        time.sleep(0.5)


# ---- the run ----------------------------------------------------------------------------

def _warm_up(garbler: str, evaluator: str, tls_dir: str, plan: Plan) -> None:
    """Runs of every circuit in each scheme, WARM_AT_ONCE at a time (lanes, every worker
    thread), before the clock starts: the daemons load (or compile) the circuits and
    build what a fleet needs then, which is start-up, not soak (``idle_before`` is
    measured after it)."""
    from snail_client.secure import AsyncSecureRunner
    from snail_common.loc.pipeline import Options

    ids = {Options(algorithm=a, min_invocations=plan.min_invocations).spec(n).registry_id
           for a in plan.algorithms for n in plan.points}

    async def warm(scheme: str) -> None:
        async with AsyncSecureRunner(garbler, evaluator, tls_dir, scheme=scheme) as runner:
            for circuit_id in sorted(ids):
                n_inputs = registry.interface(circuit_id).n_inputs
                await asyncio.gather(*(runner.run(circuit_id, np.frombuffer(
                    os.urandom(n_inputs), np.uint8) & 1 == 1) for _ in range(WARM_AT_ONCE)))

    for scheme in SCHEMES:
        asyncio.run(warm(scheme))


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
    with embedded_services(log_level="info") as services:
        tls_dir = str(services.tls_dir)
        garbler, evaluator = services.garbler_addr, services.evaluator_addr
        for name in (*(f"soak-{i:03d}" for i in range(plan.clients)), "soak-monitor"):
            add_client(tls_dir, name)
        _warm_up(garbler, evaluator, tls_dir, plan)
        pids = {d.role: d.process.pid for d in (services.garbler, services.evaluator)}
        monitor = SecureRunner(garbler, evaluator, tls_dir, cert_name="soak-monitor")
        try:
            before = _idle_before(monitor, pids)
            elapsed = _fleet(plan, ctx, pids, monitor, tally, quiet,
                             ClientJob(0, garbler, evaluator, tls_dir, "", plan, 0.0))
            after = _until_idle(monitor, pids, before, IDLE_LIMIT_S)
        finally:
            monitor.close()
        logs = {d.role: daemon_log(d.log) for d in (services.garbler, services.evaluator)}
        if keep_logs is not None:
            keep_logs.mkdir(parents=True, exist_ok=True)
            for d in (services.garbler, services.evaluator):
                shutil.copyfile(d.log, keep_logs / f"{d.role}.log")
    report = summarize(tally, plan, elapsed, before, after)
    report["soak"]["daemon_logs"] = logs
    return report


class _Fleet:
    """The client processes, each reporting on its own pipe; with ``plan.kill_every_s``,
    one at random is killed (SIGKILL) that often and a fresh one starts with its
    certificate, as a device that lost power and came back would."""

    def __init__(self, plan: Plan, ctx, template: ClientJob, start: float) -> None:
        self.plan, self.ctx, self.template, self.start = plan, ctx, template, start
        self.running: dict[int, tuple[mp.Process, Connection]] = {}
        self.certs: dict[int, str] = {}  # each client's certificate name
        self.next_index = 0
        self.killed = 0
        self.next_kill = start + plan.kill_every_s if plan.kill_every_s else math.inf

    def launch(self, cert_name: str) -> None:
        reader, writer = self.ctx.Pipe(duplex=False)
        job = dataclasses.replace(self.template, index=self.next_index, cert_name=cert_name,
                                  start=self.start)
        proc = self.ctx.Process(target=client_main, args=(job, writer), daemon=True)
        proc.start()
        writer.close()  # the child's copy is the one that writes
        self.running[self.next_index] = (proc, reader)
        self.certs[self.next_index] = cert_name
        self.next_index += 1

    def maybe_kill(self, now: float) -> None:
        """Kill one client if its time has come (only while clients start new frames)."""
        if now < self.next_kill or now >= self.start + self.plan.minutes * 60 \
                or not self.running:
            return
        self.next_kill += self.plan.kill_every_s
        index = secrets.choice(list(self.running))
        proc, reader = self.running.pop(index)
        proc.kill()
        proc.join(10)
        reader.close()
        self.killed += 1
        self.launch(self.certs[index])

    def ended(self, index: int) -> None:
        proc, reader = self.running.pop(index)
        reader.close()
        proc.join(10)

    def stop(self) -> None:
        for proc, reader in self.running.values():
            if proc.is_alive():
                proc.terminate()
            proc.join(10)
            reader.close()
        self.running.clear()


def _fleet(plan: Plan, ctx, pids: dict[str, int], monitor: SecureRunner, tally: Tally,
           quiet: bool, template: ClientJob) -> float:
    """Start the sampler and the client processes, take their reports until all are
    done; returns the seconds from the start to the last client's end."""
    start = time.monotonic()
    stop = threading.Event()
    sampler = threading.Thread(target=_sampler, args=(
        pids, monitor, start, plan.sample_s, tally, stop), daemon=True)
    sampler.start()
    fleet = _Fleet(plan, ctx, template, start)
    try:
        for i in range(plan.clients):
            fleet.launch(f"soak-{i:03d}")
        _collect(fleet, tally, plan, start, quiet)
        return time.monotonic() - start
    finally:
        tally.killed_clients = fleet.killed
        stop.set()
        sampler.join()
        fleet.stop()


def _collect(fleet: _Fleet, tally: Tally, plan: Plan, start: float, quiet: bool) -> None:
    """Take the clients' messages (checking frames as they come) until every client said
    done or is gone; a client that dies without a word (and was not killed by the soak)
    is a failure."""
    seconds = round(plan.minutes * 60)
    with bar(seconds, "soak", quiet, "s") as progress:
        while fleet.running:
            readers = {reader: index for index, (_, reader) in fleet.running.items()}
            for reader in wait(list(readers), timeout=0.5):
                index = readers[reader]
                if index not in fleet.running:
                    continue
                try:
                    message = reader.recv()
                except (EOFError, OSError):  # gone without saying done
                    proc = fleet.running[index][0]
                    proc.join(10)
                    tally.failures["client_died"] += 1
                    tally.failure_examples.append(f"client {index} exited with "
                                                  f"{proc.exitcode}")
                    fleet.ended(index)
                    continue
                if message[0] == "done":
                    fleet.ended(index)
                else:
                    _absorb(message, tally, plan)
            fleet.maybe_kill(time.monotonic())
            progress.n = min(seconds, round(time.monotonic() - start))
            if fleet.killed:
                progress.set_postfix_str(f"{fleet.killed} clients killed", refresh=False)
            progress.refresh()
