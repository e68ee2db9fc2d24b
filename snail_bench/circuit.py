"""Size, depth and build time of a localization circuit (``snail-bench circuit``).

AND gates are the garbling cost (32 bytes each on the wire), AND-depth and steps the
fixed per-step cost of the engine; ``build_s`` is a fresh build (the cache is bypassed).
"""

from __future__ import annotations

import time

from snail_common.circuit.schedule import schedule_circuit
from snail_common.pnp.sil import CLIENT
from snail_common.pnp.spec import Spec, build


def circuit_report(spec: Spec) -> dict:
    start = time.perf_counter()
    circuit = build(spec)
    built = time.perf_counter()
    schedule = schedule_circuit(circuit)
    scheduled = time.perf_counter()
    counts = circuit.counts()
    return {"circuit": {
        "algorithm": spec.algorithm, "mode": spec.mode, "points": spec.points,
        "solve": "client" if spec.solver == CLIENT else "circuit",
        "solver": spec.solver, "arith": spec.arith, "and": counts["and"], "xor": counts["xor"],
        "not": counts["not"], "depth": circuit.depth(), "steps": len(schedule.steps()),
        "build_s": round(built - start, 3), "schedule_s": round(scheduled - built, 3)}}
