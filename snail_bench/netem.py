"""Secure invocations over shaped links (``snail-bench netem``).

The three roles run as three hosts in the network lab (``snail_bench.netlab``); before
each measurement every link's RTT and rate are measured (so a reader sees the shaping
took effect), then ``snail-bench service`` runs unchanged in the client's namespace
against the daemons in theirs. By default the same lab first runs unshaped, with the same
daemons and circuits, so the two figures differ only by the shaping.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import asdict
from pathlib import Path

from snail_client.progress import bar
from snail_common.pnp.sil import CLIENT
from snail_common.pnp.spec import Spec

from .netlab.namespaces import LINKS, Lab, LabError, Shape
from .netlab.services import LabServices, lab_services


def netem_report(specs: list[Spec], repeat: int, shapes: Mapping[str, Shape],
                 baseline: bool = True, measure_seconds: float = 1.0,
                 congestion: str | None = None, slow_start_after_idle: bool | None = None,
                 quiet: bool = True,
                 on_done: Callable[[str, dict], object] | None = None) -> dict:
    """``{"netem": {"shaping", "tcp", "links", "service"[, "unshaped": {"links",
    "service"}]}}``: configured shaping per link, the TCP settings in force (``congestion``
    and ``slow_start_after_idle`` set them inside the lab; None: the kernel's), measured
    RTT and rate per link, and the service report (FORMATS.md) run from the client's
    namespace."""
    shaped = {link: shapes.get(link, Shape()) for link in LINKS}
    phases = ([("unshaped", {link: Shape() for link in LINKS})] if baseline else []) + \
        [("shaped", shaped)]
    tcp, results = run_phases(specs, repeat, phases, measure_seconds, congestion,
                              slow_start_after_idle, quiet, on_done)
    report = {"shaping": {link: asdict(shape) for link, shape in shaped.items()},
              "tcp": tcp, **results["shaped"]}
    if baseline:
        report["unshaped"] = results["unshaped"]
    return {"netem": report}


def run_phases(specs: list[Spec], repeat: int, phases: list[tuple[str, Mapping[str, Shape]]],
               measure_seconds: float = 1.0, congestion: str | None = None,
               slow_start_after_idle: bool | None = None, quiet: bool = True,
               on_done: Callable[[str, dict], object] | None = None,
               ) -> tuple[dict, dict[str, dict]]:
    """One lab, one pair of daemons, and per phase (a name and the shaping of the links
    it names; others unshaped): measured links, then the service report. Returns the TCP
    settings in force and ``{phase: {"links", "service"}}``."""
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="snail-netem-") as tmp, Lab() as lab:
        lab.tune_tcp(congestion, slow_start_after_idle)  # before any daemon connects
        tcp = lab.tcp_settings()
        with lab_services(lab, Path(tmp)) as services, \
                bar(len(phases) * (len(LINKS) + 1), "netem", quiet, "step") as progress:
            for name, phase in phases:
                lab.shape({link: phase.get(link, Shape()) for link in LINKS})
                links = {}
                for link in LINKS:
                    links[link] = lab.measure(link, measure_seconds)
                    progress.update(1)
                service = run_service(lab, services, specs, repeat)
                progress.update(1)
                results[name] = {"links": links, **service}
                if on_done is not None:
                    on_done(name, results[name])
    return tcp, results


def run_service(lab: Lab, services: LabServices, specs: list[Spec], repeat: int) -> dict:
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
               str(repeat), *services.client_args(), "--json"]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            tail = proc.stderr.strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
            raise LabError(f"snail-bench service in the client's namespace failed: {tail[0]}")
        report.update(json.loads(proc.stdout)["service"])
    return {"service": report}
