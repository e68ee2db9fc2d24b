"""Secure invocations over shaped links (``snail-bench netem``).

The three roles run as three hosts in the network lab (``snail_bench.netlab``); before
each measurement every link's RTT and rate are measured (so a reader sees the shaping
took effect), then ``snail-bench service`` runs unchanged in the client's namespace
against the daemons in theirs. By default the same lab, daemons and circuits first run
unshaped over the direct path (kernel bridges, nothing in user space) and then as the
control run: every link through the shaper with zero delay and no rate. The control run
against the unshaped one is what the lab itself costs; the shaped run against the control
run is what the shaping costs. Headline figures are wall times; the forwarder's CPU
seconds (``wire_cpu_s``) say how much of the machine the lab took.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path

from snail_client.progress import bar
from snail_common.pnp.sil import CLIENT
from snail_common.pnp.spec import Spec

from .linkbound import bounded
from .netlab.hosts import bdp_buffer, tcp_settings, tune_tcp
from .netlab.namespaces import LINKS, Lab, LabError, Shape
from .netlab.services import LabServices, lab_services


@dataclass(frozen=True)
class Phase:
    """One measurement: a name, the shaping of the links it names (others unshaped),
    and whether it is a control run (every link through the shaper, zero shaping)."""

    name: str
    shapes: Mapping[str, Shape] = field(default_factory=dict)
    control: bool = False


def netem_report(specs: list[Spec], repeat: int, shapes: Mapping[str, Shape],
                 baseline: bool = True, measure_seconds: float = 1.0,
                 congestion: str | None = None, slow_start_after_idle: bool | None = None,
                 quiet: bool = True,
                 on_done: Callable[[str, dict], object] | None = None,
                 shaper: str = "auto", control: bool = True,
                 scheme: str | None = None, localize: int = 0,
                 profile: str | None = None) -> dict:
    """``{"netem": {"profile", "shaping", "tcp", "shaper", "forwarder", "links",
    "service", "wire_cpu_s"[, "localization"][, "unshaped": {...}][, "control":
    {...}]}}``: configured shaping per link, the TCP settings in force (``congestion``
    and ``slow_start_after_idle`` set them inside the lab; None: the kernel's), the
    shaper used, measured RTT and rate per link, the service report (FORMATS.md) run
    from the client's namespace with ``--scheme scheme`` (None: its default), and the
    forwarder's CPU
    seconds over it. ``localize`` > 0: that many whole padded localizations per circuit
    (after one to warm up) in the shaped and unshaped runs, each circuit's median run
    against its link bound (linkbound.py) under ``"localization"``."""
    shaped = {link: shapes.get(link, Shape()) for link in LINKS}
    phases = [Phase("unshaped")] if baseline else []
    phases += [Phase("control", control=True)] if control else []
    phases.append(Phase("shaped", shaped))
    tcp, lab, results = run_phases(specs, repeat, phases, measure_seconds, congestion,
                                   slow_start_after_idle, quiet, on_done, shaper,
                                   scheme, localize)
    report = {"profile": profile,
              "shaping": {link: asdict(shape) for link, shape in shaped.items()},
              "tcp": tcp, **lab, **results["shaped"]}
    for name in ("unshaped", "control"):
        if name in results:
            report[name] = results[name]
    return {"netem": report}


def run_phases(specs: list[Spec], repeat: int, phases: list[Phase | tuple],
               measure_seconds: float = 1.0, congestion: str | None = None,
               slow_start_after_idle: bool | None = None, quiet: bool = True,
               on_done: Callable[[str, dict], object] | None = None,
               shaper: str = "auto", scheme: str | None = None,
               localize: int = 0) -> tuple[dict, dict, dict[str, dict]]:
    """One lab, one pair of daemons, and per phase (a Phase, or a (name, shapes) pair):
    measured links, then the service report and the forwarder's CPU seconds over it.
    Returns the TCP settings in force, ``{"shaper", "forwarder"}`` (the shaper the lab
    chose; the forwarder that ran, "native" or "python", or None) and ``{phase:
    {"links", "service", "wire_cpu_s"[, "localization"]}}`` (localizations in every
    phase but the control run, when ``localize`` > 0)."""
    results: dict[str, dict] = {}
    phases = [p if isinstance(p, Phase) else Phase(*p) for p in phases]
    forwarders: set[str] = set()
    with tempfile.TemporaryDirectory(prefix="snail-netem-") as tmp, Lab(shaper) as lab:
        # before any daemon connects; buffers for the largest bandwidth-delay product
        # of any phase, as an operator sizes them for the links the servers have
        buffers = max(bdp_buffer(dict(phase.shapes)) for phase in phases) or None
        tune_tcp(lab, congestion, slow_start_after_idle, buffers)
        tcp = tcp_settings(lab)
        steps = len(LINKS) + 1 + (1 if localize else 0)
        with lab_services(lab, Path(tmp)) as services, \
                bar(len(phases) * steps, "netem", quiet, "step") as progress:
            for phase in phases:
                lab.shape({link: phase.shapes.get(link, Shape()) for link in LINKS},
                          control=phase.control)
                links = {}
                for link in LINKS:
                    links[link] = lab.measure(link, measure_seconds)
                    progress.update(1)
                cpu = lab.wire_cpu_s()
                service = run_service(lab, services, specs, repeat, scheme)
                results[phase.name] = {"links": links, **service,
                                       "wire_cpu_s": round(lab.wire_cpu_s() - cpu, 3)}
                if localize and not phase.control:
                    results[phase.name]["localization"] = {
                        spec.circuit_id: bounded(run_localization(
                            lab, services, spec.points, localize, scheme), links)
                        for spec in specs}
                    progress.update(1)
                if lab.running_wire():
                    forwarders.add(lab.forwarder)
                progress.update(1)
                if on_done is not None:
                    on_done(phase.name, results[phase.name])
        chosen = lab.shaper
    forwarder = "python" if "python" in forwarders else (forwarders.pop() if forwarders
                                                         else None)
    return tcp, {"shaper": chosen, "forwarder": forwarder}, results


def run_localization(lab: Lab, services: LabServices, points: int, repeat: int,
                     scheme: str | None = None) -> dict:
    """``linkbound.py`` in the client's namespace: ``repeat`` padded localizations of a
    ``points``-point scene (after one to warm up), the median run's figures."""
    cmd = [*lab.exec_prefix("client"), sys.executable, "-m", "snail_bench.linkbound",
           "--points", str(points), "--repeat", str(repeat), *services.client_args(),
           *(("--scheme", scheme) if scheme else ())]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        tail = proc.stderr.strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
        raise LabError(f"a localization in the client's namespace failed: {tail[0]}")
    return json.loads(proc.stdout)


def run_service(lab: Lab, services: LabServices, specs: list[Spec], repeat: int,
                scheme: str | None = None) -> dict:
    """``snail-bench service`` in the client's namespace against the lab's daemons: its
    ``{"service": ...}`` report."""
    report: dict[str, dict] = {}
    families: dict[tuple[str, str, str], list[int]] = {}
    for spec in specs:
        families.setdefault((spec.algorithm, spec.mode, spec.solver), []).append(spec.points)
    for (algorithm, mode, solver), points in families.items():
        cmd = [*lab.exec_prefix("client"), sys.executable, "-m", "snail_bench.cli", "-q",
               "service", "--algorithm", algorithm, "--mode", mode,
               *(("--solve", "client") if solver == CLIENT
                 else ("--solve", "circuit", "--solver", solver)),
               *(arg for n in points for arg in ("--points", str(n))), "--repeat",
               str(repeat), *services.client_args(),
               *(("--scheme", scheme) if scheme else ()), "--json"]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            tail = proc.stderr.strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
            raise LabError(f"snail-bench service in the client's namespace failed: {tail[0]}")
        report.update(json.loads(proc.stdout)["service"])
    return {"service": report}
