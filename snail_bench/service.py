"""End-to-end pace of secure invocations (``snail-bench service``).

What a user waits for: the wall time of one secure run of a localization circuit, client
to both servers and back over TLS, plus the bytes on each link. Inputs are random bits:
garbling does the same work whatever the data. As in a localization, the runs share a
random frame (the inputs but the pose), whose labels go ahead with each prepared session,
and each run has a fresh random pose. The first run of each circuit is
reported apart (``first_s``), since a freshly started daemon also loads the circuit then.
With the embedded daemons the servers' peak RSS is read from /proc (Linux).

With ``clients`` > 1, that many clients (each its own pair of TLS connections, as separate
devices would have) invoke the same circuit at once: after one warm-up run each, all start
together and the report adds the total invocations per second and each client's median.
"""

from __future__ import annotations

import asyncio
import secrets
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from snail_client.blocking import SecureRunner
from snail_client.embedded import connected
from snail_client.progress import bar
from snail_client.secure import AsyncSecureRunner
from snail_client.sessions import FixedInputs, Invocation
from snail_common.circuit import registry
from snail_common.circuit.ir import Interface
from snail_common.loc.backends import frame_wires
from snail_common.net.linkrates import AUTO
from snail_common.pnp.spec import Spec

from .choices import link_args


def service_report(specs: list[Spec], repeat: int, garbler: str | None = None,
                   evaluator: str | None = None, tls_dir: str | None = None,
                   clients: int = 1, lane_window_ms: float | None = None,
                   quiet: bool = True,
                   on_done: Callable[[str, dict], object] | None = None,
                   scheme: str = AUTO, table_link: str | None = None) -> dict:
    """``{"service": {circuit_id: {...}}}``: per circuit, the first run and ``repeat``
    warm runs (median, min, max wall seconds), bytes per link and server timings of one
    run, and (embedded daemons only) each server's peak RSS so far: a high-water mark
    over the daemon's life, so with several circuits it covers the largest run yet."""
    report: dict[str, dict] = {}
    lanes = () if lane_window_ms is None else ("--lane-window-ms", str(lane_window_ms))
    with connected(garbler, evaluator, tls_dir, lanes + link_args(table_link),
                   scheme=scheme) as (runner, services), \
            bar(len(specs), "circuits", quiet, "circuit") as progress:
        for spec in specs:
            report[spec.circuit_id] = _measure(runner, spec, repeat)
            if clients > 1:
                report[spec.circuit_id].update(_fleet(runner, spec, repeat, clients))
            if services is not None:
                report[spec.circuit_id]["peak_rss_mb"] = {
                    daemon.role: _peak_rss_mb(daemon.process.pid)
                    for daemon in (services.garbler, services.evaluator)}
            progress.update(1)
            if on_done is not None:
                on_done(spec.circuit_id, report[spec.circuit_id])
        link = runner.health("evaluator").get("table_link", "tls")
    return {"service": report, "table_link": link}


def _measure(runner: SecureRunner, spec: Spec, repeat: int) -> dict:
    iface = registry.interface(spec.registry_id)
    rng = np.random.default_rng(secrets.randbits(128))
    fixed = _frame(iface, rng)

    def once() -> Invocation:
        return runner.invoke(spec.registry_id, _pose_bits(fixed, rng))

    first = once()
    runner.expect(spec.registry_id, repeat, fixed)  # garble ahead, as a padded frame does
    warm = [once() for _ in range(repeat)]
    walls = [run.wall_s for run in warm]
    # what the network and the protocol add to the evaluator's own work (client round
    # trip, tables not yet there): its evaluation less its wait for table frames, so the
    # server link's share stays in; steadier than wall time on a shared machine
    waits = [run.timing.get("evaluator_wait_s", 0.0) for run in warm]
    beyond = [run.wall_s - run.timing.get("evaluator_evaluate_s", 0.0) + wait
              for run, wait in zip(warm, waits)]
    schemes = sorted({run.scheme for run in warm})
    timeline = _timeline(warm)
    return {"and": iface.counts["and"], "depth": iface.depth, "first_s": round(first.wall_s, 4),
            "median_s": round(statistics.median(walls), 4), "min_s": round(min(walls), 4),
            "max_s": round(max(walls), 4), "repeat": repeat,
            "median_beyond_evaluate_s": round(statistics.median(beyond), 4),
            "evaluator_wait_s": round(statistics.median(waits), 4),
            "scheme": schemes[0] if len(schemes) == 1 else "+".join(schemes),
            **({"timeline_ms": timeline} if timeline else {}),
            "traffic": warm[-1].traffic,
            "timing": {k: round(v, 4) for k, v in warm[-1].timing.items()}}


# a session's events in the daemons' timelines, in the order they should happen
TIMELINE = (("garbler_t_first_sent", "first table sent"),
            ("evaluator_t_first_received", "first table received"),
            ("garbler_t_garbled", "last table garbled"),
            ("garbler_t_last_sent", "last table sent"),
            ("evaluator_t_last_received", "last table received"),
            ("evaluator_t_labels", "client's labels in"),
            ("evaluator_t_eval_end", "evaluation done"))


def _timeline(runs: list[Invocation]) -> dict[str, float]:
    """Median milliseconds from the garbler's receipt of each session's request to each
    event of its timeline (both daemons' clocks: one host here, synchronized across
    hosts), over ``runs``: where a session's time went."""
    out = {}
    for key, name in TIMELINE:
        offsets = [run.timing[key] - run.timing["garbler_t_request"] for run in runs
                   if key in run.timing and "garbler_t_request" in run.timing]
        if offsets:
            out[name] = round(statistics.median(offsets) * 1000, 2)
    return out


def _fleet(runner: SecureRunner, spec: Spec, repeat: int, clients: int) -> dict:
    """``clients`` concurrent clients, ``repeat`` runs each after one warm-up: total
    invocations per second over the measured phase and each client's median seconds."""
    garbler, evaluator, tls_dir = runner.endpoints
    iface = registry.interface(spec.registry_id)

    async def fleet() -> tuple[float, list[float]]:
        started = asyncio.Barrier(clients + 1)

        async def client() -> float:
            rng = np.random.default_rng(secrets.randbits(128))
            fixed = _frame(iface, rng)
            async with AsyncSecureRunner(garbler, evaluator, tls_dir,
                                         scheme=runner.scheme) as r:
                def bits() -> np.ndarray:
                    return _pose_bits(fixed, rng)

                await r.invoke(spec.registry_id, bits())
                await started.wait()
                r.expect(spec.registry_id, repeat, fixed)
                walls = [(await r.invoke(spec.registry_id, bits())).wall_s
                         for _ in range(repeat)]
                return statistics.median(walls)

        tasks = [asyncio.ensure_future(client()) for _ in range(clients)]
        barrier = asyncio.ensure_future(started.wait())
        await asyncio.wait([barrier, *tasks], return_when=asyncio.FIRST_COMPLETED)
        if not barrier.done():  # a client failed before the measured phase: say why
            barrier.cancel()
            await asyncio.gather(*tasks)  # raises the first failure; the rest go with it
        t0 = time.perf_counter()
        medians = await asyncio.gather(*tasks)
        return time.perf_counter() - t0, medians

    elapsed, medians = asyncio.run(fleet())
    return {"clients": clients, "throughput_inv_per_s": round(clients * repeat / elapsed, 2),
            "client_median_s": [round(m, 4) for m in medians]}


def _frame(iface: Interface, rng: np.random.Generator) -> FixedInputs:
    """A random frame: the bits a localization's invocations share (all but the pose)."""
    mask = frame_wires(iface)
    return FixedInputs(mask, rng.integers(0, 2, iface.n_inputs).astype(bool) & mask)


def _pose_bits(frame: FixedInputs, rng: np.random.Generator) -> np.ndarray:
    """One invocation's input bits: the frame's, and a random pose."""
    bits = rng.integers(0, 2, frame.mask.size).astype(bool)
    bits[frame.mask] = frame.bits[frame.mask]
    return bits


def _peak_rss_mb(pid: int) -> float | None:
    """VmHWM of a live process in MB, or None where /proc does not have it."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        pass
    return None
