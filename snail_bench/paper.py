"""The paper's evaluation on this machine (``snail-bench paper``).

Measures what each of the paper's figures shows, with our circuits and daemons, and keeps
the paper's own numbers (``shared/paper_results.json``) beside ours; ``paper_plot`` draws
the figures and writes the report. What is measured and how:

- ``totals``: SIL vs DO, one whole localization, n = 6..12, on loopback (the paper ran
  both parties on one host). A SIL localization makes at least 20 invocations (the
  privacy floor), so its total is the first invocation plus 19 warm ones (median); a DO
  localization is one invocation of the 20-iteration circuit. Our DO is LM only, and
  the quick plan leaves it out (each n compiles for ~2 minutes and runs for ~20 s).
- ``sweep``: seconds per iteration and bytes garbler -> evaluator per iteration vs n, in
  the network lab at 0 and 5 ms one way between the servers, 2.5 Gbit/s (the paper's
  setting). Without root the lab cannot be built: the sweep then runs on loopback at 0 ms
  only, and ``results["sweep"]["lab"]`` says why.
- ``latency``: n = 6 LM, seconds per iteration vs added one-way delay (0, 5, 20, 50 ms)
  on the server link and on the client's links; the slope over 2 delays per round trip
  is the number of round trips an invocation waits for.
- ``ops``: float32 operations per iteration vs n, counted on the circuit's float32
  mirror (every add, sub, mul, div, ... on every element), next to the paper's formulas.
- ``micro``: seconds for 10,000 garbled operations (add, mul) on float32, int32 and
  int64, garbled and evaluated in one process (the paper's float vs integer table),
  extrapolated from two batch sizes.
"""

from __future__ import annotations

import json
import os
import secrets
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from snail_common.arith import integer, multiply
from snail_common.arith.catalog import OPS
from snail_common.circuit import CircuitBuilder, schedule_circuit
from snail_common.gc.run import garbled_run
from snail_common.net.parent import child_env
from snail_common.pnp.fops import F, MirrorBackend
from snail_common.pnp.sil import input_shapes
from snail_common.pnp.spec import Spec, program

from .headline import provenance

PAPER_RESULTS = Path(__file__).resolve().parents[2] / "shared" / "paper_results.json"
SERVER_RATE_MBIT = 2500.0  # the paper's link between its two servers
MIN_INVOCATIONS = 20  # a SIL localization's privacy floor (snail-client's default)
LATENCY_DELAYS_MS = (0.0, 5.0, 20.0, 50.0)
# invocations per circuit in the lab's sweeps, as many as a localization makes: the client
# sizes its garble-ahead from its first invocations, so five warm runs measure the
# pipeline filling (n = 6 at 5 ms: 2.0x unshaped at 5 runs, 0.83x at 20, 2026-11-27)
LAB_REPEAT = MIN_INVOCATIONS
PROFILE_REPEAT = 3  # localizations per network profile and n, after one to warm up
MICRO_OPS = 10_000  # the paper's micro-benchmark size


@dataclass(frozen=True)
class Plan:
    """What one run measures."""

    totals_points: tuple[int, ...]
    do_points: tuple[int, ...]
    sweep_points: tuple[int, ...]
    algorithms: tuple[str, ...]
    repeat: int
    micro_lanes: int  # operations per garbled micro-benchmark circuit
    profile_points: tuple[int, ...] = (6, 12, 64)  # a localization per network profile

    @property
    def lab_repeat(self) -> int:
        """Invocations per circuit in a lab sweep: at least a localization's count, since
        the client sizes its garble-ahead from its first invocations."""
        return max(self.repeat, LAB_REPEAT)

    def expected_minutes(self) -> float:
        """A rough forecast on 2 cores with a cold circuit cache: a DO circuit compiles in
        about 100 s and runs in about 20 s; a SIL circuit costs ~0.05 s per point to build
        and ~(0.15 + 0.005 n) s per run."""
        runs = len(self.algorithms) * (MIN_INVOCATIONS * len(self.totals_points)
                                       + 2 * (self.lab_repeat + 1)
                                       * len(self.sweep_points))
        sil_s = sum(0.05 * n * 10 for n in {*self.totals_points, *self.sweep_points}) \
            * len(self.algorithms)
        mean_n = np.mean([*self.totals_points, *self.sweep_points])
        run_s = runs * (0.15 + 0.005 * mean_n)
        do_s = len(self.do_points) * 140
        latency_s = 7 * 12
        # per profile: a lab, links measured, and per n 1 + PROFILE_REPEAT localizations
        profiles_s = 4 * (15 + len(self.profile_points) * (1 + PROFILE_REPEAT) * 8)
        return round((sil_s + run_s + do_s + latency_s + profiles_s) / 60 + 1, 1)


QUICK = Plan(totals_points=(6, 12), do_points=(), sweep_points=(6, 56), algorithms=("lm",),
             repeat=3, micro_lanes=500, profile_points=(6, 12))
FULL = Plan(totals_points=tuple(range(6, 13)), do_points=tuple(range(6, 13)),
            sweep_points=(6, 56, 106, 156, 206, 256), algorithms=("lm", "gn"), repeat=5,
            micro_lanes=1000)


def load_paper(path: Path = PAPER_RESULTS) -> dict:
    """The paper's numbers; ValueError naming the file if it cannot be read."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read the paper's numbers ({exc})") from None


def measure_all(plan: Plan, tick: Callable[[str], object] = lambda _: None) -> dict:
    """Every measurement of ``plan``; ``tick(name)`` after each step (a progress bar)."""
    from .service import service_report

    results: dict = {"plan": asdict(plan), "started": time.strftime("%Y-%m-%d %H:%M:%S")}
    results["ops"] = {alg: {n: op_counts(sil_spec(alg, n)) for n in plan.sweep_points}
                      for alg in plan.algorithms}
    tick("ops")
    results["micro"] = micro_benchmark(plan.micro_lanes)
    tick("micro")
    sil = [sil_spec(alg, n) for alg in plan.algorithms for n in plan.totals_points]
    # compiled first, as a deployed pair has them: a localization's first invocation
    # otherwise holds the compile (n = 7: 3.7 s against 0.44 s once cached)
    precompile(_unique(sil + [sil_spec(alg, n) for alg in plan.algorithms
                              for n in (*plan.sweep_points, *plan.profile_points)]))
    rows = service_report(_unique(sil), MIN_INVOCATIONS - 1)["service"]
    results["totals"] = {"sil": {f"{spec.algorithm}-{spec.circuit_id}":
                                 _sil_total(rows[spec.circuit_id], spec) for spec in sil}}
    tick("sil totals")
    do = [Spec("lm", "do", "ldlt", n) for n in plan.do_points]
    precompile(do)  # a DO circuit compiles for minutes: not inside a run's timeout
    rows = service_report(do, 1)["service"] if do else {}
    results["totals"]["do"] = {spec.circuit_id: {"algorithm": "lm", "n": spec.points,
                                                 "total_s": rows[spec.circuit_id]["median_s"],
                                                 "and": rows[spec.circuit_id]["and"]}
                               for spec in do}
    tick("do totals")
    results["sweep"] = sweep(plan)
    tick("sweep")
    results["latency"] = latency_sweep(plan.lab_repeat)
    tick("latency")
    results["profiles"] = profiles(plan.profile_points)
    tick("profiles")
    results["finished"] = time.strftime("%Y-%m-%d %H:%M:%S")
    return results


def sil_spec(algorithm: str, n: int) -> Spec:
    """The SIL circuit ``snail-client localize`` runs for ``algorithm`` at ``n`` points by
    default (with the client solve, LM and GN share one circuit)."""
    from snail_common.loc.pipeline import Options

    return Options(algorithm=algorithm, mode="sil").spec(n)


def _unique(specs: list[Spec]) -> list[Spec]:
    """``specs`` without a second spec of the same circuit."""
    return list({spec.circuit_id: spec for spec in specs}.values())


COMPILE_CHILD = ("import sys; from snail_common.net.parent import exit_with_parent; "
                 "exit_with_parent(); from snail_common import families; "
                 "families.register_all(); from snail_common.circuit import registry; "
                 "registry.compiled(sys.argv[1])")


def precompile(specs: list[Spec]) -> None:
    """Compile ``specs`` into the circuit cache, each in a process of its own (a DO
    circuit peaks at gigabytes; this process should not keep them) that ends with this
    one: a run stopped mid-compile leaves no compiler behind."""
    for spec in specs:
        proc = subprocess.run([sys.executable, "-c", COMPILE_CHILD, spec.registry_id],
                              capture_output=True, text=True,
                              env={**os.environ, **child_env()})
        if proc.returncode != 0:
            tail = proc.stderr.strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
            raise RuntimeError(f"compiling {spec.circuit_id} failed: {tail[0]}")


def _sil_total(row: dict, spec: Spec) -> dict:
    total = row["first_s"] + (MIN_INVOCATIONS - 1) * row["median_s"]
    return {"algorithm": spec.algorithm, "n": spec.points, "total_s": round(total, 3),
            "per_iteration_s": row["median_s"], "and": row["and"]}


def sweep(plan: Plan) -> dict:
    """Per iteration seconds and bytes vs n at 0 and 5 ms between the servers."""
    from .netem import run_phases
    from .netlab.namespaces import LabUnavailable, Shape
    from .service import service_report

    specs = [sil_spec(alg, n) for alg in plan.algorithms for n in plan.sweep_points]
    phases = [(f"{d:g}ms", {"garbler_evaluator": Shape(d, rate_mbit=SERVER_RATE_MBIT)})
              for d in (0.0, 5.0)]
    try:
        tcp, shaper, phase_rows = run_phases(_unique(specs), plan.lab_repeat,
                                             phases)
        lab: str | dict = {"tcp": tcp, **shaper,
                           "links": {k: v["links"] for k, v in phase_rows.items()}}
        rows = {name: row["service"] for name, row in phase_rows.items()}
    except LabUnavailable as exc:
        lab = f"unavailable: {exc}; 0 ms measured on loopback, 5 ms not measured"
        rows = {"0ms": service_report(_unique(specs), plan.lab_repeat)["service"]}
    out: dict = {"lab": lab, "series": {}}
    for phase, service in rows.items():
        for spec in specs:
            row = service[spec.circuit_id]
            out["series"].setdefault(f"{spec.algorithm}_{phase}", []).append(
                {"n": spec.points, "per_iteration_s": row["median_s"], "and": row["and"],
                 "bytes": row["traffic"]["garbler_to_evaluator"]})
    return out


def latency_sweep(repeat: int) -> dict:
    """n = 6 LM per iteration vs one-way delay on each link class; round trips read off
    the slope (least squares over the delays; a round trip costs 2 delays)."""
    from .netem import Phase, run_phases
    from .netlab.namespaces import LabUnavailable, Shape

    client = ("client_garbler", "client_evaluator")
    # 0 ms through the forwarder too (a control run), so the slope is the delay's alone
    phases: list = [Phase("server_0ms", control=True)]
    phases += [(f"server_{d:g}ms", {"garbler_evaluator": Shape(d)})
               for d in LATENCY_DELAYS_MS[1:]]
    phases += [(f"client_{d:g}ms", {link: Shape(d) for link in client})
               for d in LATENCY_DELAYS_MS[1:]]
    try:
        # the kernel's own TCP, as users get it: the client's links run cubic from their
        # first packet (net/conn.py), so a burst of labels takes one round trip
        spec = sil_spec("lm", 6)
        tcp, shaper, rows = run_phases([spec], repeat, phases)
    except LabUnavailable as exc:
        return {"lab": f"unavailable: {exc}"}
    out: dict = {"tcp": tcp, **shaper, "delays_ms": list(LATENCY_DELAYS_MS)}
    for side in ("server", "client"):
        names = ["server_0ms"] + [f"{side}_{d:g}ms" for d in LATENCY_DELAYS_MS[1:]]
        per_it = [rows[name]["service"][spec.circuit_id]["median_s"] for name in names]
        beyond = [rows[name]["service"][spec.circuit_id]["median_beyond_evaluate_s"]
                  for name in names]
        rtt = [rows[name]["links"]["client_evaluator" if side == "client" else
                                   "garbler_evaluator"]["rtt_ms"] for name in names]
        slope = float(np.polyfit(LATENCY_DELAYS_MS, per_it, 1)[0]) * 1000  # s per s
        slope_beyond = float(np.polyfit(LATENCY_DELAYS_MS, beyond, 1)[0]) * 1000
        out[side] = {"per_iteration_s": per_it, "beyond_evaluate_s": beyond,
                     "measured_rtt_ms": rtt,
                     "round_trips": round(slope / 2, 2),
                     "round_trips_beyond_evaluate": round(slope_beyond / 2, 2)}
    return out


def profiles(points: tuple[int, ...]) -> dict:
    """A padded LM localization at each of ``points`` under each network profile
    (``snail-bench netem --profile NAME --localize``): its wall time against the bound
    its links set. ``{profile: {"links", "shaper", "forwarder", "localization": {n:
    {...}}}}``, or ``{"lab": "unavailable: ..."}`` without the network lab."""
    from .netem import Phase, run_phases
    from .netlab.namespaces import LabUnavailable
    from .netlab.profiles import PROFILES, profile_shapes

    specs = [sil_spec("lm", n) for n in points]
    out: dict = {"points": list(points), "repeat": PROFILE_REPEAT}
    try:
        for name in PROFILES:
            _, shaper, rows = run_phases(specs, 1, [Phase(name, profile_shapes(name))],
                                         localize=PROFILE_REPEAT)
            row = rows[name]
            out[name] = {"links": row["links"], **shaper, "localization": {
                str(spec.points): row["localization"][spec.circuit_id] for spec in specs}}
    except LabUnavailable as exc:
        return {"lab": f"unavailable: {exc}"}
    return out


class _CountingMirror(MirrorBackend):
    """The float32 mirror, counting each operation once per element it computes."""

    def __init__(self) -> None:
        super().__init__()
        self.counts: Counter[str] = Counter()

    def _count(self, name: str, value: np.ndarray) -> np.ndarray:
        self.counts[name] += int(np.size(value))
        return value

    def add(self, x, y):
        return self._count("add", super().add(x, y))

    def sub(self, x, y):
        return self._count("sub", super().sub(x, y))

    def mul(self, x, y):
        return self._count("mul", super().mul(x, y))

    def mul_const(self, x, c: float):
        return self._count("mul", super().mul_const(x, c))

    def div(self, x, y):
        return self._count("div", super().div(x, y))

    def sqrt(self, x):
        return self._count("sqrt", super().sqrt(x))

    def lt(self, x, y):
        return self._count("compare", super().lt(x, y))


def op_counts(spec: Spec) -> dict[str, int]:
    """float32 operations of one iteration of ``spec``'s algorithm, by kind, as the paper
    counts them: a fixed-point circuit is counted as its float twin (the same operations,
    its per-point ones on integers)."""
    spec = replace(spec, arith="float")
    be = _CountingMirror()
    rng = np.random.default_rng(0)  # the counts do not depend on the values
    inputs = {name: F(be, rng.standard_normal(shape).astype(np.float32))
              for name, shape in input_shapes(spec.algorithm, spec.points,
                                                spec.solver).items()}
    program(spec, inputs)
    return dict(sorted(be.counts.items()))


def _int_op(op: str, bits: int) -> Callable:
    if op == "add":
        return lambda b, x, y: integer.add(b, x, y)
    return lambda b, x, y: multiply.mul(b, x, y)[..., :bits]  # the low word, as C does


def _garble_seconds(op: Callable, bits: int, lanes: int) -> tuple[float, int]:
    """Seconds to garble and evaluate ``lanes`` independent ``op``s, and AND per op."""
    b = CircuitBuilder()
    x, y = (b.input(name, (lanes,), bits=bits) for name in "xy")
    b.output("z", op(b, x, y))
    circuit = b.build()
    schedule = schedule_circuit(circuit)
    bits_in = np.frombuffer(secrets.token_bytes(schedule.n_inputs), np.uint8) & 1
    t0 = time.perf_counter()
    garbled_run(schedule, bits_in.astype(bool))
    return time.perf_counter() - t0, circuit.counts()["and"] // lanes


def micro_benchmark(lanes: int) -> dict:
    """Seconds for 10,000 garbled add and mul on float32, int32 and int64 (garbling and
    evaluation in this process) and AND per op. 10,000 int64 products would be 45 M AND
    gates at once, so each op runs at ``lanes`` and 2 x ``lanes`` and the time is
    extrapolated along that line: a fixed per-step part (the circuit's depth) plus a part
    per operation."""
    out: dict = {}
    for kind, bits in (("float32", 32), ("int32", 32), ("int64", 64)):
        for op in ("add", "mul"):
            fn = OPS[op][0] if kind == "float32" else _int_op(op, bits)
            t1, and_per_op = _garble_seconds(fn, bits, lanes)
            t2, _ = _garble_seconds(fn, bits, 2 * lanes)
            per_op = max(t2 - t1, 0.0) / lanes
            fixed = max(t1 - per_op * lanes, 0.0)
            out.setdefault(kind, {})[op] = {
                "and_per_op": and_per_op,
                "seconds_10000": round(fixed + per_op * MICRO_OPS, 4),
                "measured_s": {lanes: round(t1, 4), 2 * lanes: round(t2, 4)}}
    return out

def write_paper(out: Path, plan: Plan, paper: dict, quiet: bool = True) -> Path:
    """Measure ``plan``, then write ``out``/results.json, the PNGs and report.md (the
    figures are checked for matplotlib before anything is measured)."""
    from snail_client.progress import bar

    from . import paper_plot

    paper_plot._pyplot()  # ImportError now, not after the measurements
    out.mkdir(parents=True, exist_ok=True)
    with bar(8, "paper", quiet, "step") as progress:
        def tick(name: str) -> None:
            progress.set_postfix_str(name)
            progress.update(1)

        results = {**measure_all(plan, tick), **provenance()}  # commit, machine: headline.py
        (out / "results.json").write_text(json.dumps(results, indent=1))
        sections = paper_plot.write_figures(json.loads(json.dumps(results)), paper, out)
        tick("figures")
    head = (f"# The paper's evaluation on this machine\n\nMeasured {results['started']} to "
            f"{results['finished']} by `snail-bench paper` ({'quick' if plan == QUICK else 'full'}"
            f" plan: {plan}). Paper: {paper.get('source', '')}\n")
    report = out / "report.md"
    report.write_text(head + "\n" + "\n\n".join(sections) + "\n")
    return report
