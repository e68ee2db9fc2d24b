"""A plan as the kernel's program: flat int64 ops over row descriptors, every index checked.

The native kernel walks the same plan as the numpy runner (circuit/plan.py), so gates are
numbered, blocked and laid out in the stream exactly as there: each AND piece is cut into
blocks of the stream's block size (an op each, its tables one block), linear groups are
ops, and a step whose results must wait (not ``direct``) computes into scratch rows and
publishes them after its last op, as the numpy runner does.

The kernel checks nothing, so everything it follows is checked here, once per (plan,
block size): every slot index against the slot count, every scratch row against the
scratch size, every ragged group's term bounds. A call then checks only its op range and
its buffers' sizes (native/engine.py). Index lists are used where they lie (the plan
keeps them alive, memory-mapped from the cache for stored plans): no copies.
"""

from __future__ import annotations

from bisect import bisect_right
from typing import NamedTuple

import numpy as np

from snail_common.circuit.plan import AndPlan, LinearPlan, Plan, RaggedGroup
from snail_common.circuit.slots import Rows, length

from ..stream import table_words

OP_AND, OP_XOR, OP_RAGGED, OP_PUBLISH = 0, 1, 2, 3
OP_KIND, OP_PARALLEL = 0xFF, 0x100  # kind word: the kind | rows may run on several threads
PAR_MIN_AND = 1024  # kernel.c's: smaller AND ops are never cut, so never checked
OP_WORDS = 6  # kind, n, first (gate number | columns), rows, dst, aux
R_SLICE, R_I32, R_I64 = 0, 1, 2


class Program(NamedTuple):
    ops: np.ndarray  # int64 (n_ops, OP_WORDS)
    rows: np.ndarray  # int64 (n_rows, 3)
    n_slots: int
    scratch_rows: int
    and_gates: np.ndarray  # int64 (n_ops,): gates of each op (0 for linear ops)
    keep: tuple  # the arrays the row descriptors point into

    @property
    def n_ops(self) -> int:
        return len(self.ops)

    def table_words(self, scheme: int) -> np.ndarray:
        """int64 (n_ops + 1,): table words before each op (the last: the whole run's)."""
        n = self.and_gates
        per = np.where(n > 0, table_words(scheme, n), 0)
        return np.concatenate([[0], np.cumsum(per)]).astype(np.int64)


def ops_within(cum: np.ndarray, lo: int, words: int) -> int:
    """The end of the longest op range from ``lo`` whose tables take at most ``words``."""
    return bisect_right(cum, int(cum[lo]) + words, lo) - 1


class _Builder:
    def __init__(self, n_slots: int) -> None:
        self.n_slots = n_slots
        self.ops: list[tuple[int, int, int, int, int, int]] = []
        self.rows: list[tuple[int, int, int]] = []
        self.keep: list[np.ndarray] = []
        self.scratch = 0  # rows of scratch the widest waiting step needs

    def check(self, rows: Rows, n: int, limit: int | None = None) -> None:
        """Raise ValueError unless the first ``n`` of ``rows`` are in 0 .. limit-1
        (default: slots)."""
        limit = self.n_slots if limit is None else limit
        if isinstance(rows, slice):
            step = 0 if rows.step is None else rows.step
            if step < 0 or rows.start < 0 or (n and rows.start + step * (n - 1) >= limit):
                raise ValueError(f"plan rows {rows} leave 0 .. {limit - 1} within {n} rows")
            if step and length(rows) < n:
                raise ValueError(f"plan rows {rows} name fewer than {n} rows")
            return
        if rows.dtype not in (np.int32, np.int64) or not rows.flags.c_contiguous:
            raise ValueError(f"plan index lists must be contiguous int32/int64, got "
                             f"{rows.dtype}")
        if len(rows) < n:
            raise ValueError(f"a plan index list has {len(rows)} rows, {n} needed")
        if n and (int(rows[:n].min()) < 0 or int(rows[:n].max()) >= limit):
            raise ValueError(f"a plan index list leaves 0 .. {limit - 1}")

    def row(self, rows: Rows) -> None:
        """Append the descriptor of checked ``rows``: an index list with a constant step
        (a strided column, or one slot repeated) becomes a slice, which the kernel reads
        without loading an index per row."""
        if not isinstance(rows, slice):
            rows = _as_run(rows)
        if isinstance(rows, slice):
            self.rows.append((R_SLICE, rows.start, 0 if rows.step is None else rows.step))
            return
        self.keep.append(rows)
        self.rows.append((R_I32 if rows.dtype == np.int32 else R_I64, rows.ctypes.data, 0))

    def op(self, kind: int, n: int, first: int, rows: int, dst: int, aux: int = 0) -> None:
        self.ops.append((kind, n, first, rows, dst, aux))


def _as_run(idx: np.ndarray) -> Rows:
    """``idx`` as slice(first, ..., step) when its steps are one constant >= 0 (step 0:
    slice(first, first + 1) with no step, the kernel's repeated slot), else ``idx``."""
    if len(idx) < 2:
        return idx
    first, step = int(idx[0]), int(idx[1]) - int(idx[0])
    if step < 0 or int(idx[-1]) != first + step * (len(idx) - 1) \
            or not np.all(np.diff(idx) == step):
        return idx
    return slice(first, first + 1) if step == 0 else \
        slice(first, first + step * (len(idx) - 1) + 1, step)


def _part_view(rows: Rows, k: int, m: int) -> Rows:
    """Rows k .. k+m-1 (a view for index lists: the descriptor points into the piece's)."""
    if isinstance(rows, slice):
        if rows.step is None:
            return rows
        start = rows.start + k * rows.step
        return slice(start, start + (m - 1) * rows.step + 1, rows.step)
    return rows[k : k + m]


def build_program(plan: Plan, n_slots: int, block: int) -> Program:
    """The kernel program of ``plan`` over ``n_slots`` slots, AND pieces in blocks of at
    most ``block`` gates (see the module docstring). ValueError on an index out of range."""
    if block < 1:
        raise ValueError(f"block must be positive, got {block}")
    b = _Builder(n_slots)
    gates = 0
    for step in plan.steps:
        if isinstance(step, AndPlan):
            if step.first != gates:
                raise ValueError(f"AND piece numbered from {step.first}, expected {gates}")
            _and_piece(b, step, block)
            gates += step.n
        elif isinstance(step, LinearPlan):
            _linear_step(b, step)
        else:
            raise ValueError(f"unknown plan step {type(step).__name__}")
    ops = np.array(b.ops, np.int64).reshape(-1, OP_WORDS)
    and_gates = np.where(ops[:, 0] & OP_KIND == OP_AND, ops[:, 1], 0) if len(ops) else \
        np.zeros(0, np.int64)
    return Program(ops, np.array(b.rows, np.int64).reshape(-1, 3), n_slots, b.scratch,
                   and_gates.astype(np.int64), tuple(b.keep))


def _and_piece(b: _Builder, step: AndPlan, block: int) -> None:
    n = step.n
    for r in (step.out, step.a, step.b):  # the whole piece's indices, checked once
        b.check(r, n)
    dst = -1 if step.direct else 0  # a piece that waits computes into scratch rows 0 .. n-1
    kind = OP_AND | (OP_PARALLEL if _rows_independent(step, b.n_slots) else 0)
    for k in range(0, n, block):
        m = min(block, n - k)
        at = len(b.rows)
        for r in (step.out, step.a, step.b):
            b.row(_part_view(r, k, m))
        b.op(kind, m, step.first + k, at, dst if dst < 0 else k)
    if not step.direct:
        b.scratch = max(b.scratch, n)
        at = len(b.rows)
        b.row(step.out)
        b.op(OP_PUBLISH | OP_PARALLEL, n, 0, at, 0)


def _indices(rows: Rows, n: int) -> np.ndarray:
    if isinstance(rows, slice):
        step = 0 if rows.step is None else rows.step
        return rows.start + step * np.arange(n) if step else np.full(n, rows.start)
    return rows[:n]


def _rows_independent(step: AndPlan, n_slots: int) -> bool:
    """Whether the piece's gates may run in any order, on several threads: it writes
    scratch rows (not direct), or no gate reads a slot that one of its gates writes (a
    direct piece may read a slot before a later row writes it: order matters there).
    Pieces too small to be cut are not checked (False)."""
    if not step.direct:
        return True
    if step.n < PAR_MIN_AND:
        return False
    written = np.zeros(n_slots, bool)
    written[_indices(step.out, step.n)] = True
    return not (written[_indices(step.a, step.n)].any()
                or written[_indices(step.b, step.n)].any())


def _linear_step(b: _Builder, step: LinearPlan) -> None:
    used = 0  # scratch rows of a step whose results wait
    pending: list[tuple[int, int, int]] = []  # (rows, n, scratch row) to publish
    for g in step.groups:
        n = length(g.out)
        at = len(b.rows)
        b.check(g.out, n)
        b.row(g.out)
        if isinstance(g, RaggedGroup):
            terms, starts = g.terms, g.starts
            if len(starts) != n or (n and (int(starts[0]) < 0 or int(starts[-1]) >= len(terms)
                                          or np.any(np.diff(starts) <= 0))):
                raise ValueError("a ragged group's starts are not increasing within its terms")
            for r, k, limit in ((terms, len(terms), None), (starts, n, len(terms))):
                b.check(r, k, limit)
                b.row(r)
            b.op(OP_RAGGED | OP_PARALLEL, n, 0, at, -1 if step.direct else used, len(terms))
        else:
            if not g.columns:
                raise ValueError("a linear group has no columns")
            for col in g.columns:
                b.check(col, n)
                b.row(col)
            b.op(OP_XOR | OP_PARALLEL, n, len(g.columns), at, -1 if step.direct else used)
        if not step.direct:
            pending.append((at, n, used))
            used += n
    for at, n, row in pending:
        b.op(OP_PUBLISH | OP_PARALLEL, n, 0, at, row)
    b.scratch = max(b.scratch, used)
