"""Executable form of a Schedule for the garbling engine, built once per schedule and cached.

Every slot list of a step becomes a ``Rows`` (a slice when its slots are consecutive, which
the schedule's allocator makes common), so contiguous operands are read as views and
contiguous outputs written in place instead of scattered. A step is *direct* when its results may
be written while it still reads (a linear step: it reads none of the slots it writes; an AND
step: no block reads a slot that an earlier block writes); otherwise all of its results are
computed before any is written (outputs may reuse operand slots).

A wide linear step whose outputs have different term counts would need ``reduceat``,
several times slower than dense gathers once its temporary outgrows the caches; the plan
regroups its outputs by term count so every group is a dense set of columns (one slot list
per term). Ragged steps with few terms per column keep ``reduceat``: there the number of
numpy calls dominates. Garbler and evaluator run the same
plan.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from snail_common.circuit.memo import per_object
from snail_common.circuit.schedule import AndStep, LinearStep, Schedule

from .slots import Rows, as_rows, gather, part, slot_view, write

U64 = np.uint64


class Scratch:
    """Growable work buffers of one executor: never shared between runs or threads."""

    def __init__(self) -> None:
        self._bufs: dict[str, np.ndarray] = {}

    def get(self, name: str, n: int) -> np.ndarray:
        """A (n, 2) uint64 buffer, reused across calls with the same name."""
        buf = self._bufs.get(name)
        if buf is None or len(buf) < n:
            buf = self._bufs[name] = np.empty((n, 2), U64)
        return buf[:n]


class LinearGroup(NamedTuple):
    out: Rows  # slots written
    columns: tuple[Rows, ...]  # columns[k][i]: k-th term of output i

    def xor_into(self, labels: np.ndarray, dst: np.ndarray, scratch: Scratch) -> None:
        """dst = XOR of the group's columns."""
        n, cols = len(dst), self.columns
        first = gather(labels, cols[0], scratch.get("t0", n))
        if len(cols) == 1:
            np.copyto(dst, first)
            return
        np.bitwise_xor(first, gather(labels, cols[1], scratch.get("t1", n)), out=dst)
        for col in cols[2:]:
            np.bitwise_xor(dst, gather(labels, col, scratch.get("t0", n)), out=dst)


class LinearPlan(NamedTuple):
    groups: tuple[LinearGroup, ...]
    direct: bool

    def run(self, labels: np.ndarray, slots: np.ndarray, scratch: Scratch) -> None:
        """Apply in place."""
        if not self.direct:  # outputs may reuse slots read here: compute all, then write
            accs = [scratch.get(f"acc{i}", _length(g.out)) for i, g in enumerate(self.groups)]
            for g, acc in zip(self.groups, accs):
                g.xor_into(labels, acc, scratch)
            for g, acc in zip(self.groups, accs):
                write(labels, slots, g.out, acc)
            return
        for g in self.groups:
            if isinstance(g.out, slice):
                g.xor_into(labels, labels[g.out], scratch)
            else:
                acc = scratch.get("acc", len(g.out))
                g.xor_into(labels, acc, scratch)
                slots[g.out] = slot_view(acc)


class RaggedPlan(NamedTuple):
    """A linear step with mixed term counts and few terms per count: one gather and one
    reduceat cost fewer numpy calls than a dense group per count."""

    out: Rows
    terms: np.ndarray
    starts: np.ndarray

    def run(self, labels: np.ndarray, slots: np.ndarray, scratch: Scratch) -> None:
        acc = np.bitwise_xor.reduceat(labels.take(self.terms, axis=0), self.starts, axis=0)
        write(labels, slots, self.out, acc)


class AndPlan(NamedTuple):
    out: Rows
    a: Rows
    b: Rows
    first: int  # global index of the step's first AND gate (its tweak base)
    n: int
    direct: bool  # outputs may be written block by block (see _ReadRows.reads_precede_writes)


class AndOutputs:
    """Where the kernel writes an AND step's output labels, block by block: in place for a
    direct step with consecutive output slots, else through a block or whole-step buffer."""

    def __init__(self, labels: np.ndarray, slots: np.ndarray, block: int) -> None:
        self._labels, self._slots = labels, slots
        self._block = np.empty((block, 2), U64)
        self._step = np.empty((0, 2), U64)

    def target(self, step: AndPlan, k: int, m: int) -> np.ndarray:
        """The (m, 2) array to receive the labels of gates k .. k+m-1."""
        if step.direct:
            if isinstance(step.out, slice):
                return self._labels[part(step.out, k, m)]
            return self._block[:m]
        if len(self._step) < step.n:
            self._step = np.empty((step.n, 2), U64)
        return self._step[k : k + m]

    def store(self, step: AndPlan, k: int, m: int) -> None:
        """Publish gates k .. k+m-1 (a non-direct step publishes after its last block)."""
        if step.direct:
            if not isinstance(step.out, slice):
                self._slots[step.out[k : k + m]] = slot_view(self._block[:m])
        elif k + m == step.n:
            write(self._labels, self._slots, step.out, self._step[: step.n])


class Plan(NamedTuple):
    steps: tuple[AndPlan | LinearPlan | RaggedPlan, ...]


def _length(rows: Rows) -> int:
    return rows.stop - rows.start if isinstance(rows, slice) else len(rows)


class _ReadRows:
    """Where a step reads the slots it writes (one reusable per-slot array per build; a
    range of outputs is checked with comparisons instead)."""

    def __init__(self, n_slots: int) -> None:
        self._last = np.full(n_slots, -1, np.int32)  # last row of the step reading a slot

    def disjoint(self, out: np.ndarray, reads: np.ndarray) -> bool:
        """No slot of ``out`` is in ``reads``."""
        rows = as_rows(out)
        if isinstance(rows, slice):
            return not bool(((reads >= rows.start) & (reads < rows.stop)).any())
        self._last[reads] = 0
        hit = bool((self._last[out] >= 0).any())
        self._last[reads] = -1
        return not hit

    def reads_precede_writes(self, out: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
        """Every slot out[i] is read, if at all, only by rows <= i: block by block writes
        cannot clobber a later block's operands, whatever the block size (an executor reads
        a whole block before writing it)."""
        rows = np.arange(len(out), dtype=np.int32)
        span = as_rows(out)
        if isinstance(span, slice):  # out[i] = start + i
            return all(bool((ops - span.start >= rows)[(ops >= span.start)
                                                      & (ops < span.stop)].all())
                       for ops in (a, b))
        for ops in (a, b):
            np.maximum.at(self._last, ops, rows)
        ok = bool((self._last[out] <= rows).all())
        self._last[a] = -1
        self._last[b] = -1
        return ok


def _build(schedule: Schedule) -> Plan:
    """The plan of ``schedule``, built on first use and kept while the schedule lives."""
    reads = _ReadRows(schedule.n_slots)
    steps = []
    gates = 0  # AND rows so far: the next step's first gate number (its tweak base)
    for i, step in enumerate(schedule.steps()):
        if isinstance(step, AndStep):
            if int(schedule.step_lo[i]) != gates:
                raise ValueError(f"AND step {i} starts at row {schedule.step_lo[i]}, not "
                                 f"{gates}: gate numbers (hash tweaks) would repeat")
            steps.append(AndPlan(as_rows(step.out), as_rows(step.a), as_rows(step.b),
                                 gates, len(step.out),
                                 reads.reads_precede_writes(step.out, step.a, step.b)))
            gates += len(step.out)
        else:
            steps.append(_linear(step, reads.disjoint(step.out, step.terms)))
    if gates != schedule.n_and:
        raise ValueError(f"AND steps cover {gates} of {schedule.n_and} AND rows")
    return Plan(tuple(steps))


# A dense group costs a few numpy calls per column (~1 us each) and ~2 ns per term; reduceat
# costs ~3 ns per term while its temporary fits the caches and ~10 ns beyond. Measured
# crossover: a few hundred terms per column.
DENSE_MIN_TERMS_PER_COLUMN = 512


def _linear(step: LinearStep, direct: bool) -> LinearPlan | RaggedPlan:
    t, w = step.terms, step.width
    if not step.out.size:
        return LinearPlan((), direct)
    if w:  # columns as strided views: take() converts them to intp copies anyway
        return LinearPlan((LinearGroup(as_rows(step.out),
                                       tuple(as_rows(t[k::w]) for k in range(w))),), direct)
    counts = np.diff(np.append(step.starts, len(t)))
    if np.any(counts == 0):
        raise ValueError("a linear step output has no terms")
    sizes = np.flatnonzero(np.bincount(counts))
    if len(t) < DENSE_MIN_TERMS_PER_COLUMN * int(sizes.sum()):
        return RaggedPlan(as_rows(step.out), step.terms, step.starts)
    order = np.argsort(counts, kind="stable")
    groups = []
    for c in sizes.tolist():
        rows = order[counts[order] == c]
        first = step.starts[rows]
        groups.append(LinearGroup(as_rows(step.out[rows]),
                                  tuple(as_rows(t[first + k]) for k in range(c))))
    return LinearPlan(tuple(groups), direct)


plan_for = per_object(_build)
