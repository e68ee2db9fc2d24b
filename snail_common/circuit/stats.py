"""Circuit statistics: what the gate budgets, benchmarks and the engine's cost model read."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from .ir import Circuit
from .schedule import AND_STEP, Schedule


@dataclass(frozen=True)
class CircuitStats:
    and_gates: int
    xor_gates: int
    not_gates: int
    and_depth: int
    steps: int
    and_steps: int
    linear_steps: int
    peak_slots: int
    xor_terms: int

    def to_dict(self) -> dict[str, int]:
        return asdict(self)


def circuit_stats(circuit: Circuit, schedule: Schedule) -> CircuitStats:
    counts = circuit.counts()
    and_steps = int((schedule.step_kind == AND_STEP).sum())
    return CircuitStats(
        and_gates=counts["and"], xor_gates=counts["xor"], not_gates=counts["not"],
        and_depth=circuit.depth(), steps=schedule.n_steps, and_steps=and_steps,
        linear_steps=schedule.n_steps - and_steps, peak_slots=schedule.n_slots,
        xor_terms=len(schedule.lin_terms))
