"""Executable form of a Schedule, built once per schedule and cached: what the schedule
runner (runner.py) walks for cleartext evaluation, garbling and evaluation alike (only
the AND kernel differs, so the three cannot drift apart).

Every step is cut into pieces: runs of rows whose slot columns are arithmetic (runs.py),
read as views and written in place, and the rows left over, gathered and scattered.
A linear piece XORs a dense set of columns (one slot list per term); leftover linear rows
of mixed term counts with few terms per count use one gather and one ``reduceat``
instead, where the number of numpy calls dominates. AND pieces of one step follow each
other, and gates are numbered (hash tweaks, table order) in plan order.

A step is *direct* when its results may be written while it still reads (a linear step:
it reads none of the slots it writes; an AND step: no row reads a slot that an earlier
row writes); otherwise its results are all computed before any is written. Schedules
from ``schedule_circuit`` never write a slot a step reads; older ones may.
"""

from __future__ import annotations

from itertools import pairwise
from typing import NamedTuple

import numpy as np

from .memo import per_object
from .runs import MIN_RUN, find_runs, run_slice
from .schedule import AndStep, LinearStep, Schedule
from .slots import Rows, as_rows, gather, length, part, slot_view, write

U64 = np.uint64


class Scratch:
    """Growable work buffers of one executor: never shared between runs or threads."""

    def __init__(self, width: int) -> None:
        self.width = width
        self._bufs: dict[str, np.ndarray] = {}

    def get(self, name: str, n: int) -> np.ndarray:
        """A (n, width) uint64 buffer, reused across calls with the same name."""
        buf = self._bufs.get(name)
        if buf is None or len(buf) < n:
            buf = self._bufs[name] = np.empty((n, self.width), U64)
        return buf[:n]


class RunGroup(NamedTuple):
    """out[i] = XOR over k of columns[k][i], every column a run: views, no gathers."""

    out: slice
    columns: tuple[slice, ...]

    def compute(self, values: np.ndarray, dst: np.ndarray, scratch: Scratch) -> None:
        cols = self.columns
        if len(cols) == 1:
            np.copyto(dst, values[cols[0]])
            return
        np.bitwise_xor(values[cols[0]], values[cols[1]], out=dst)
        for col in cols[2:]:
            np.bitwise_xor(dst, values[col], out=dst)


class LinearGroup(NamedTuple):
    """out[i] = XOR over k of columns[k][i], columns gathered."""

    out: Rows
    columns: tuple[Rows, ...]

    def compute(self, values: np.ndarray, dst: np.ndarray, scratch: Scratch) -> None:
        n, cols = len(dst), self.columns
        first = gather(values, cols[0], scratch.get("t0", n))
        if len(cols) == 1:
            np.copyto(dst, first)
            return
        np.bitwise_xor(first, gather(values, cols[1], scratch.get("t1", n)), out=dst)
        for col in cols[2:]:
            np.bitwise_xor(dst, gather(values, col, scratch.get("t0", n)), out=dst)


class RaggedGroup(NamedTuple):
    """Rows of mixed term counts: out[i] = XOR of values[terms[starts[i]:starts[i+1]]]."""

    out: Rows
    terms: np.ndarray
    starts: np.ndarray

    def compute(self, values: np.ndarray, dst: np.ndarray, scratch: Scratch) -> None:
        np.bitwise_xor.reduceat(values.take(self.terms, axis=0), self.starts, axis=0,
                                out=dst)


class LinearPlan(NamedTuple):
    groups: tuple[RunGroup | LinearGroup | RaggedGroup, ...]
    direct: bool

    def run(self, values: np.ndarray, slots: np.ndarray, scratch: Scratch) -> None:
        """Apply in place."""
        if not self.direct:  # outputs may reuse slots read here: compute all, then write
            accs = [scratch.get(f"acc{i}", length(g.out)) for i, g in enumerate(self.groups)]
            for g, acc in zip(self.groups, accs):
                g.compute(values, acc, scratch)
            for g, acc in zip(self.groups, accs):
                write(values, slots, g.out, acc)
            return
        for g in self.groups:
            if isinstance(g.out, slice):
                g.compute(values, values[g.out], scratch)
            else:
                acc = scratch.get("acc", len(g.out))
                g.compute(values, acc, scratch)
                slots[g.out] = slot_view(acc)


class AndPlan(NamedTuple):
    """AND gates first .. first+n-1 (plan order): out[i] = a[i] AND b[i]."""

    out: Rows
    a: Rows
    b: Rows
    first: int  # number of the piece's first AND gate (its tweak base)
    n: int
    direct: bool  # outputs may be written block by block (see _ReadRows.reads_precede_writes)


class AndOutputs:
    """Where a kernel writes an AND piece's outputs, block by block: in place for a direct
    piece with arithmetic output slots, else through a block or whole-piece buffer."""

    def __init__(self, values: np.ndarray, slots: np.ndarray, block: int) -> None:
        self._values, self._slots = values, slots
        width = values.shape[1]
        self._block = np.empty((block, width), U64)
        self._step = np.empty((0, width), U64)

    def target(self, step: AndPlan, k: int, m: int) -> np.ndarray:
        """The (m, W) array to receive the values of gates k .. k+m-1."""
        if step.direct:
            if isinstance(step.out, slice):
                return self._values[part(step.out, k, m)]
            return self._block[:m]
        if len(self._step) < step.n:
            self._step = np.empty((step.n, self._values.shape[1]), U64)
        return self._step[k : k + m]

    def store(self, step: AndPlan, k: int, m: int) -> None:
        """Publish gates k .. k+m-1 (a non-direct piece publishes after its last block)."""
        if step.direct:
            if not isinstance(step.out, slice):
                self._slots[step.out[k : k + m]] = slot_view(self._block[:m])
        elif k + m == step.n:
            write(self._values, self._slots, step.out, self._step[: step.n])


class Plan(NamedTuple):
    steps: tuple[AndPlan | LinearPlan, ...]
    max_and_step: int  # the widest AND piece, in gates


class _ReadRows:
    """Where a step reads the slots it writes (one reusable per-slot array per build; a
    range of outputs is checked with comparisons instead). A schedule that promises
    ``disjoint_io`` is taken at its word."""

    def __init__(self, n_slots: int, disjoint_io: bool = False) -> None:
        self._known = disjoint_io
        self._last = np.full(0 if disjoint_io else n_slots, -1, np.int32)

    def disjoint(self, out: np.ndarray, reads: np.ndarray) -> bool:
        """No slot of ``out`` is in ``reads``."""
        if self._known:
            return True
        rows = as_rows(out)
        if isinstance(rows, slice) and rows.step == 1:
            return not bool(((reads >= rows.start) & (reads < rows.stop)).any())
        self._last[reads] = 0
        hit = bool((self._last[out] >= 0).any())
        self._last[reads] = -1
        return not hit

    def reads_precede_writes(self, out: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
        """Every slot out[i] is read, if at all, only by rows <= i: block by block writes
        cannot clobber a later block's operands, whatever the block size (an executor reads
        a whole block before writing it)."""
        if self._known:
            return True
        rows = np.arange(len(out), dtype=np.int32)
        span = as_rows(out)
        if isinstance(span, slice) and span.step == 1:  # out[i] = start + i
            return all(bool((ops - span.start >= rows)[(ops >= span.start)
                                                      & (ops < span.stop)].all())
                       for ops in (a, b))
        for ops in (a, b):
            np.maximum.at(self._last, ops, rows)
        ok = bool((self._last[out] <= rows).all())
        self._last[a] = -1
        self._last[b] = -1
        return ok


# A separate piece costs a kernel call: ~3 numpy calls for a bitwise AND or an XOR group,
# ~25 for a garbling kernel; a gathered row costs a few ns. So single-word rows (cleartext)
# take runs from MIN_RUN rows on, labels only long ones (measured on the SIL circuits).
LABEL_MIN_RUN = {"and": 4096, "linear": 512}


def _build(schedule: Schedule, strided: bool) -> Plan:
    """The plan of ``schedule`` (strided runs or only adjacent ones, see slots.py)."""
    min_run = ({"and": MIN_RUN, "linear": MIN_RUN} if strided else LABEL_MIN_RUN)
    reads = _ReadRows(schedule.n_slots, schedule.disjoint_io)
    steps: list[AndPlan | LinearPlan] = []
    gates = 0  # AND rows so far: the next piece's first gate number (its tweak base)
    for i, step in enumerate(schedule.steps()):
        if isinstance(step, AndStep):
            if int(schedule.step_lo[i]) != gates:
                raise ValueError(f"AND step {i} starts at row {schedule.step_lo[i]}, not "
                                 f"{gates}: gate numbers (hash tweaks) would repeat")
            steps.extend(_and_pieces(step, gates, reads, strided, min_run["and"]))
            gates += len(step.out)
        else:
            steps.append(_linear(step, reads.disjoint(step.out, step.terms), strided,
                                 min_run["linear"]))
    if gates != schedule.n_and:
        raise ValueError(f"AND steps cover {gates} of {schedule.n_and} AND rows")
    widest = max((p.n for p in steps if isinstance(p, AndPlan)), default=0)
    return Plan(tuple(steps), widest)


def _and_pieces(step: AndStep, first: int, reads: _ReadRows, strided: bool,
                min_run: int) -> list[AndPlan]:
    """An AND step as its runs, then its leftover rows (numbered in that order). A step
    whose writes may clobber its own reads stays one piece in schedule order."""
    out, a, b = step.out, step.a, step.b
    if not reads.reads_precede_writes(out, a, b):
        return [AndPlan(as_rows(out), as_rows(a), as_rows(b), first, len(out), False)]
    runs, rest = find_runs(out, [a, b], strided, min_run)
    columns = [tuple(run_slice(c, r0, r1) for c in (out, a, b)) for r0, r1 in runs]
    if rest.size:
        columns.append(tuple(as_rows(c[rest], strided) for c in (out, a, b)))
    pieces = []
    for rows in columns:
        pieces.append(AndPlan(*rows, first, length(rows[0]), True))
        first += pieces[-1].n
    return pieces


# A dense group costs a few numpy calls per column (~1 us each) and ~2 ns per term; reduceat
# costs ~3 ns per term while its temporary fits the caches and ~10 ns beyond. Measured
# crossover: a few hundred terms per column.
DENSE_MIN_TERMS_PER_COLUMN = 512


def _linear(step: LinearStep, direct: bool, strided: bool, min_run: int) -> LinearPlan:
    """A linear step as runs of each term count, then its leftover rows: dense groups per
    term count, or one ragged group when they are few. The scheduler sorts a step's rows
    by term count, so each count is one range of rows and its terms one dense block."""
    t = step.terms
    if not step.out.size:
        return LinearPlan((), direct)
    counts = np.diff(np.append(step.starts, len(t)))
    if np.any(counts == 0):
        raise ValueError("a linear step output has no terms")
    bounds = [0, *(np.flatnonzero(counts[1:] != counts[:-1]) + 1).tolist(), len(counts)]
    if (len(bounds) > 2 and len(counts) < min_run
            and len(t) < DENSE_MIN_TERMS_PER_COLUMN * len(np.unique(counts))):
        return LinearPlan((RaggedGroup(as_rows(step.out, strided), t.astype(np.intp),
                                       step.starts.astype(np.intp)),), direct)
    groups: list[RunGroup | LinearGroup | RaggedGroup] = []
    left: list[tuple[np.ndarray, list[np.ndarray]]] = []  # (out, term columns)
    for r0, r1 in pairwise(bounds):
        k, t0 = int(counts[r0]), int(step.starts[r0])
        block = t[t0 : t0 + (r1 - r0) * k].reshape(r1 - r0, k)
        out, cols = step.out[r0:r1], [block[:, j] for j in range(k)]
        runs, rest = find_runs(out, cols, strided, min_run)
        for a, b in runs:
            groups.append(RunGroup(run_slice(out, a, b),
                                   tuple(run_slice(col, a, b) for col in cols)))
        if len(rest) == len(out):
            left.append((out, cols))
        elif rest.size:
            left.append((out[rest], [col[rest] for col in cols]))
    n_terms = sum(len(o) * len(cols) for o, cols in left)
    if len(left) > 1 and n_terms < DENSE_MIN_TERMS_PER_COLUMN * sum(len(c) for _, c in left):
        groups.append(_ragged(left))
    else:
        groups.extend(LinearGroup(as_rows(o, strided),
                                  tuple(as_rows(col, strided) for col in cols))
                      for o, cols in left)
    return LinearPlan(tuple(groups), direct)


def _ragged(parts: list[tuple[np.ndarray, list[np.ndarray]]]) -> RaggedGroup:
    """One reduceat over rows given as (out, term columns) pieces of any term counts."""
    out = np.concatenate([o for o, _ in parts])
    terms = np.concatenate([np.stack(cols, axis=1).ravel() for _, cols in parts])
    counts = np.concatenate([np.full(len(o), len(cols)) for o, cols in parts])
    return RaggedGroup(as_rows(out), terms.astype(np.intp),
                       (np.cumsum(counts) - counts).astype(np.intp))


# Bump when a change here changes any plan: gates are numbered (hash tweaks, table order)
# in plan order, so garbler and evaluator must use the same plan, and plans are stored
# with cached schedules (tests/test_plan_store.py pins a plan's digest).
PLAN_VERSION = 1


def _stored_or_built(schedule: Schedule, strided: bool) -> Plan:
    source = schedule.plan_source
    kind = f"v{PLAN_VERSION}-{'strided' if strided else 'adjacent'}"
    if source is None:
        return _build(schedule, strided)
    return source.get(kind, lambda: _build(schedule, strided))


_adjacent = per_object(lambda schedule: _stored_or_built(schedule, False))
_strided = per_object(lambda schedule: _stored_or_built(schedule, True))


def plan_for(schedule: Schedule, strided: bool = False) -> Plan:
    """The plan of ``schedule``, built on first use and kept while the schedule lives:
    ``strided`` for single-word rows (cleartext), adjacent runs only for labels."""
    return (_strided if strided else _adjacent)(schedule)
