"""Levelized schedule: the circuit as a short list of numpy-sized steps over reusable slots.

Two kinds of step alternate:
- AND step d: every AND gate of AND-depth d, as three slot arrays (out, a, b).
- linear step: XOR/NOT logic between AND layers, folded into multi-input XORs. Each
  materialized wire is the XOR of a list of *leaf* slots (CSR: ``ptr`` into ``terms``), so
  a whole XOR tree costs one gather + one ``bitwise_xor.reduceat`` and the schedule keeps
  about two steps per AND level however deep the XOR chains are.

A linear wire is materialized (gets a slot) only when something outside its own layer
needs it: an AND gate, a circuit output, or a linear gate of a later layer. Inside a
layer, XOR wires are expanded into their consumers. An expression longer than
``max_terms`` is cut: it is materialized in an extra sub-step and used as a leaf, which
bounds the duplicated work of shared XOR subtrees. Unused XOR logic disappears.

Slots are reused by liveness and laid out for locality (random gathers over a slot array
larger than the cache cost ~10 ns each). Walking steps backwards, each step's rows are
ordered (linear steps: by term count first) so that wires dying at the same step sit
together, in the order their last reader reads them; each such run gets one contiguous
block of slots, best fit among the blocks freed before the step (never a slot the step
itself reads, so executors may write outputs as they go). Wide, regular circuits then
read and write long runs of equally spaced slots, which executors can process as strided
views instead of gathers. Best fit wastes next to nothing (the compiler benchmark needs
its live width plus 2 slots); not reusing a step's own reads costs their count at the
peak step (there: every input is read last by the first AND step, 10.2 M slots instead
of 9.1 M). NOT is XOR with the constant-1 wire.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from .fold import AND_STEP, MAX_TERMS, fold
from .ir import Circuit
from .layout import allocate_slots, order_rows, to_slots

# Bump when schedule_circuit makes a different schedule of the same circuit: garbler and
# evaluator number AND gates (hash tweaks) in schedule order, and cached schedules are
# keyed by this (tests/test_circuit_keys.py holds the scheduler to it).
SCHEDULE_VERSION = 1


class AndStep(NamedTuple):
    out: np.ndarray
    a: np.ndarray
    b: np.ndarray


class LinearStep(NamedTuple):
    """out[i] = XOR of slots terms[starts[i] : starts[i+1]].

    ``width`` is the common term count when every output has the same one (then
    ``terms.reshape(-1, width)`` is a dense matrix), else 0.
    """

    out: np.ndarray
    terms: np.ndarray
    starts: np.ndarray
    width: int


@dataclass
class Schedule:
    """Slot-level program shared by the cleartext evaluator, garbler and evaluator.

    Slots ``0 .. n_inputs+1`` hold the constants and input bits on entry. Executors gather
    a step's operands before writing its outputs, unless ``disjoint_io`` says no step
    writes a slot that it reads (true for every schedule ``schedule_circuit`` makes).
    """

    n_inputs: int
    n_slots: int
    step_kind: np.ndarray  # uint8 (S,)
    step_lo: np.ndarray  # int64 (S,) first row in and_* (AND) or lin_out (LINEAR)
    step_hi: np.ndarray  # int64 (S,)
    and_out: np.ndarray
    and_a: np.ndarray
    and_b: np.ndarray
    lin_out: np.ndarray
    lin_ptr: np.ndarray  # int64 (M+1,) into lin_terms
    lin_terms: np.ndarray
    output_slots: np.ndarray
    disjoint_io: bool = False
    # where plans of this schedule are stored (a cache entry), if anywhere: an object
    # with get(kind, build) -> plan, see cache.py
    plan_source: Any = field(default=None, repr=False, compare=False)
    _steps: list | None = field(default=None, repr=False, compare=False)

    ARRAYS = ("step_kind", "step_lo", "step_hi", "and_out", "and_a", "and_b", "lin_out",
              "lin_ptr", "lin_terms", "output_slots")

    @property
    def n_steps(self) -> int:
        return len(self.step_kind)

    @property
    def n_and(self) -> int:
        return len(self.and_out)

    def steps(self) -> list[AndStep | LinearStep]:
        """The steps as views, built once."""
        if self._steps is None:
            self._steps = [self._step(i) for i in range(self.n_steps)]
        return self._steps

    def _step(self, i: int) -> AndStep | LinearStep:
        lo, hi = int(self.step_lo[i]), int(self.step_hi[i])
        if self.step_kind[i] == AND_STEP:
            return AndStep(self.and_out[lo:hi], self.and_a[lo:hi], self.and_b[lo:hi])
        t0, t1 = int(self.lin_ptr[lo]), int(self.lin_ptr[hi])
        starts = self.lin_ptr[lo:hi] - t0
        counts = np.diff(self.lin_ptr[lo : hi + 1])
        width = int(counts[0]) if counts.size and np.all(counts == counts[0]) else 0
        return LinearStep(self.lin_out[lo:hi], self.lin_terms[t0:t1], starts, width)

    def to_arrays(self, prefix: str = "schedule_") -> dict[str, np.ndarray]:
        d = {prefix + k: getattr(self, k) for k in self.ARRAYS}
        d[prefix + "meta"] = np.array([self.n_inputs, self.n_slots, self.disjoint_io],
                                      dtype=np.int64)
        return d

    @classmethod
    def from_arrays(cls, d, prefix: str = "schedule_") -> Schedule:
        meta = [int(v) for v in d[prefix + "meta"]]  # older files lack disjoint_io
        return cls(meta[0], meta[1], *(np.asarray(d[prefix + k]) for k in cls.ARRAYS),
                   disjoint_io=len(meta) > 2 and bool(meta[2]))


def schedule_circuit(circuit: Circuit, reuse_slots: bool = True,
                     max_terms: int = MAX_TERMS) -> Schedule:
    """Compile a circuit into a Schedule (see the module docstring)."""
    plan = fold(circuit, max_terms)
    death = order_rows(circuit, plan)
    slot_of, n_slots = allocate_slots(circuit, plan, death, reuse_slots)
    del death
    for arr in (plan.and_out, plan.and_a, plan.and_b, plan.lin_out, plan.lin_terms):
        to_slots(slot_of, arr)
    output_slots = slot_of[circuit.outputs]
    del slot_of  # before lin_ptr, 8 bytes a row: the two are the peak otherwise
    lin_ptr = np.zeros(plan.lin_lens.size + 1, np.int64)
    np.cumsum(plan.lin_lens, dtype=np.int64, out=lin_ptr[1:])
    return Schedule(
        n_inputs=circuit.n_inputs, n_slots=n_slots,
        step_kind=plan.kind, step_lo=plan.lo, step_hi=plan.hi,
        and_out=plan.and_out, and_a=plan.and_a, and_b=plan.and_b, lin_out=plan.lin_out,
        lin_ptr=lin_ptr, lin_terms=plan.lin_terms, output_slots=output_slots,
        disjoint_io=True)
