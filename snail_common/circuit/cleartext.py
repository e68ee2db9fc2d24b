"""Cleartext evaluation over a Schedule: the test oracle for every garbled run.

Runs 64 input vectors per uint64 word (bit-packed lanes), so one pass over the schedule
evaluates many inputs at once.

Random gathers over a slot array larger than the cache cost ~10 ns each, so a pass is
planned once per schedule: every step is cut into *runs*, row ranges over which the output
slot and every operand slot advance by a constant stride (the scheduler lays slots out so
that almost every row falls in a long run). A run is computed with ufuncs on strided
views of the slot array: no index arrays, no gathers, outputs written in place. The rows
left over are gathered into scratch buffers and scattered. A step whose outputs reuse a
slot the same step reads (schedules from before slots were laid out that way) computes
everything before writing anything.
"""

from __future__ import annotations

from collections.abc import Mapping
from itertools import pairwise
from typing import NamedTuple

import numpy as np

from .ir import FIRST_INPUT, Circuit, Interface
from .memo import per_object
from .schedule import AndStep, LinearStep, Schedule
from .values import from_bits, pack_lanes, to_bits, unpack_lanes

MIN_RUN = 128  # shorter runs cost more in numpy calls than their gathers do
RAGGED_ROWS = 256  # up to this many leftover XOR rows: one reduceat beats a gather per term


def _view(start: int, stride: int, n: int) -> slice:
    """The slice of the slot axis holding slots start, start+stride, ... (n of them)."""
    if stride == 0 or n == 1:
        return slice(start, start + 1)  # broadcasts against the n-row output
    stop = start + stride * (n - 1) + (1 if stride > 0 else -1)
    return slice(start, stop if stop >= 0 else None, stride)


class _RunOp(NamedTuple):
    """out[i] = op(operand_0[i], operand_1[i], ...) on strided views of the slot array."""

    out: slice
    operands: tuple[slice, ...]
    ufunc: np.ufunc

    def run(self, v: np.ndarray, defer: bool, scratch: object = None) -> np.ndarray | None:
        ops = self.operands
        if defer:
            acc = self.ufunc(v[ops[0]], v[ops[1]]) if len(ops) > 1 else v[ops[0]].copy()
        else:
            acc = v[self.out]
            if len(ops) > 1:
                self.ufunc(v[ops[0]], v[ops[1]], out=acc)
            else:
                acc[...] = v[ops[0]]
        for op in ops[2:]:
            self.ufunc(acc, v[op], out=acc)
        return acc if defer else None


class _GatherOp(NamedTuple):
    """Leftover rows with the same operand count: gathers into scratch, then a scatter."""

    out: np.ndarray  # intp slots
    operands: tuple[np.ndarray, ...]  # intp slots, one array per operand
    ufunc: np.ufunc

    def run(self, v: np.ndarray, defer: bool, scratch: tuple[np.ndarray, np.ndarray]
            ) -> np.ndarray | None:
        n = self.out.size
        acc = np.empty((n, *v.shape[1:]), v.dtype) if defer else scratch[0][:n]
        tmp = scratch[1][:n]
        v.take(self.operands[0], axis=0, out=acc)
        for op in self.operands[1:]:
            self.ufunc(acc, v.take(op, axis=0, out=tmp), out=acc)
        if defer:
            return acc
        v[self.out] = acc
        return None


class _RaggedOp(NamedTuple):
    """A few leftover XOR rows of mixed term counts: one gather and one reduceat."""

    out: np.ndarray  # intp slots
    terms: np.ndarray  # intp slots, row after row
    starts: np.ndarray  # intp: first term of each row

    def run(self, v: np.ndarray, defer: bool, scratch: object = None) -> np.ndarray | None:
        acc = np.bitwise_xor.reduceat(v.take(self.terms, axis=0), self.starts, axis=0)
        if defer:
            return acc
        v[self.out] = acc
        return None


class _StepPlan(NamedTuple):
    ops: tuple[_RunOp | _GatherOp | _RaggedOp, ...]
    defer: bool  # outputs reuse slots this step reads: compute all, then write


class _Plan(NamedTuple):
    steps: tuple[_StepPlan, ...]
    scratch_rows: int


def _build(schedule: Schedule) -> _Plan:
    """The run plan of ``schedule``, built on first use and kept while the schedule lives."""
    stamp = None if schedule.disjoint_io else np.full(schedule.n_slots, -1, np.int32)
    steps, scratch_rows = [], 0
    for i, step in enumerate(schedule.steps()):
        reads = (step.a, step.b) if isinstance(step, AndStep) else (step.terms,)
        defer = False
        if stamp is not None:
            for r in reads:
                stamp[r] = i
            defer = bool(np.any(stamp[step.out] == i))
        ops = _step_ops(step)
        scratch_rows = max([scratch_rows] + [op.out.size for op in ops
                                             if isinstance(op, _GatherOp)])
        steps.append(_StepPlan(tuple(ops), defer))
    return _Plan(tuple(steps), scratch_rows)


_plan_for = per_object(_build)


def _step_ops(step: AndStep | LinearStep) -> list[_RunOp | _GatherOp | _RaggedOp]:
    """Runs where the rows allow them; the other rows as few gather calls as possible."""
    is_and = isinstance(step, AndStep)
    if step.out.size < MIN_RUN:  # no run fits: skip looking for one
        if is_and:
            return [_GatherOp(step.out.astype(np.intp),
                              (step.a.astype(np.intp), step.b.astype(np.intp)), np.bitwise_and)]
        return [_RaggedOp(step.out.astype(np.intp), step.terms.astype(np.intp),
                          step.starts.astype(np.intp))]
    ufunc = np.bitwise_and if is_and else np.bitwise_xor
    groups = ([(step.out, [step.a, step.b])] if is_and
              else _linear_groups(step.out, step.terms, step.starts))
    ops: list[_RunOp | _GatherOp | _RaggedOp] = []
    left: dict[int, list[tuple[np.ndarray, list[np.ndarray]]]] = {}
    for out, operands in groups:
        runs, rest = _runs(out, operands, ufunc)
        ops.extend(runs)
        if rest.size:
            left.setdefault(len(operands), []).append((out[rest], [c[rest] for c in operands]))
    n_left = sum(o.size for parts in left.values() for o, _ in parts)
    if not is_and and 0 < n_left <= RAGGED_ROWS:
        ops.append(_ragged([part for parts in left.values() for part in parts]))
        left = {}
    for parts in left.values():
        out = np.concatenate([o for o, _ in parts]).astype(np.intp)
        cols = tuple(np.concatenate(c).astype(np.intp) for c in zip(*(c for _, c in parts)))
        ops.append(_GatherOp(out, cols, ufunc))
    return ops


def _ragged(parts: list[tuple[np.ndarray, list[np.ndarray]]]) -> _RaggedOp:
    """One reduceat over rows given as (out, term columns) pieces of any term counts."""
    out = np.concatenate([o for o, _ in parts]).astype(np.intp)
    terms = np.concatenate([np.stack(cols, axis=1).ravel() for _, cols in parts])
    counts = np.concatenate([np.full(o.size, len(cols)) for o, cols in parts])
    return _RaggedOp(out, terms.astype(np.intp), (np.cumsum(counts) - counts).astype(np.intp))


def _linear_groups(out: np.ndarray, terms: np.ndarray, starts: np.ndarray):
    """Maximal ranges of consecutive rows with the same term count, as (out, term columns)."""
    counts = np.diff(np.append(starts, terms.size))
    if np.any(counts <= 0):
        raise ValueError("a linear step output has no terms")
    cuts = np.concatenate([[0], np.flatnonzero(counts[1:] != counts[:-1]) + 1, [out.size]])
    for r0, r1 in pairwise(cuts.tolist()):
        k = int(counts[r0])
        t0 = int(starts[r0])
        block = terms[t0 : t0 + (r1 - r0) * k].reshape(r1 - r0, k)
        yield out[r0:r1], [block[:, j] for j in range(k)]


def _runs(out: np.ndarray, operands: list[np.ndarray],
          ufunc: np.ufunc) -> tuple[list[_RunOp], np.ndarray]:
    """Runs of at least MIN_RUN rows over which every slot column has a constant stride,
    and the rows outside them. Slots are below 2**31, so int32 differences are exact."""
    n = out.size
    covered = np.zeros(n, bool)
    runs = []
    if n >= MIN_RUN:
        cols = [out, *operands]
        same = np.ones(n, bool)  # same[r]: row r continues the stride of rows r-2, r-1
        same[:2] = False
        for c in cols:
            step = np.diff(c)
            same[2:] &= step[1:] == step[:-1]
        edge = np.flatnonzero(same[1:] != same[:-1])  # alternating starts and ends
        if same[-1]:
            edge = np.append(edge, n - 1)
        first, last = edge[0::2] - 1, edge[1::2] + 1  # rows first .. last-1 are affine
        last[:-1] = np.minimum(last[:-1], first[1:])  # neighbours share at most one row
        long = last - first >= MIN_RUN
        for r0, r1 in zip(first[long].tolist(), last[long].tolist()):
            covered[r0:r1] = True
            k = r1 - r0
            views = [_view(int(c[r0]), int(c[r0 + 1]) - int(c[r0]), k) for c in cols]
            runs.append(_RunOp(views[0], tuple(views[1:]), ufunc))
    return runs, np.flatnonzero(~covered)


def run_schedule(schedule: Schedule, input_words: np.ndarray) -> np.ndarray:
    """Evaluate on packed lanes: uint64 (n_inputs, W) -> uint64 (n_outputs, W)."""
    plan = _plan_for(schedule)
    width = input_words.shape[1] if input_words.ndim == 2 else 1
    shape = (schedule.n_slots,) if width == 1 else (schedule.n_slots, width)
    v = np.empty(shape, np.uint64)
    v[0] = 0
    v[1] = np.uint64(0xFFFFFFFFFFFFFFFF)
    v[FIRST_INPUT : FIRST_INPUT + schedule.n_inputs] = input_words.reshape(
        (schedule.n_inputs, *shape[1:]))
    scratch = (np.empty((plan.scratch_rows, *shape[1:]), np.uint64),
               np.empty((plan.scratch_rows, *shape[1:]), np.uint64))
    for step in plan.steps:
        if step.defer:
            results = [op.run(v, True, scratch) for op in step.ops]
            for op, acc in zip(step.ops, results):
                v[op.out] = acc
        else:
            for op in step.ops:
                op.run(v, False, scratch)
    return v.reshape(schedule.n_slots, width)[schedule.output_slots]


def evaluate_bits(schedule: Schedule, input_bits: np.ndarray) -> np.ndarray:
    """bool (L, n_inputs) -> bool (L, n_outputs): one row per input vector."""
    input_bits = np.atleast_2d(np.asarray(input_bits, dtype=bool))
    lanes = input_bits.shape[0]
    out = run_schedule(schedule, pack_lanes(input_bits.T))
    return unpack_lanes(out, lanes).T


def encode_inputs(circuit: Circuit | Interface, values: Mapping[str, object],
                  batch: int | None = None) -> np.ndarray:
    """Named input values -> bool (L, n_inputs); with ``batch`` every value has a leading
    batch axis of that length."""
    missing = [g.name for g in circuit.inputs if g.name not in values]
    extra = sorted(set(values) - {g.name for g in circuit.inputs})
    if missing or extra:
        raise ValueError(f"inputs missing {missing} / unknown {extra}")
    lanes = 1 if batch is None else batch
    parts = []
    for g in circuit.inputs:
        v = np.asarray(values[g.name], dtype=object if g.dtype == "int" else g.dtype)
        want = g.shape if batch is None else (batch, *g.shape)
        if v.shape != want:
            raise ValueError(f"input {g.name!r} has shape {v.shape}, expected {want}")
        parts.append(to_bits(v, g.bits, g.dtype).reshape(lanes, -1))
    return np.concatenate(parts, axis=1) if parts else np.zeros((lanes, 0), bool)


def decode_outputs(circuit: Circuit | Interface, bits: np.ndarray,
                   batch: bool = False) -> dict[str, np.ndarray]:
    """bool (L, n_outputs) -> named output values (leading batch axis if ``batch``)."""
    bits = np.atleast_2d(bits)
    out, pos = {}, 0
    for g in circuit.output_groups:
        chunk = bits[:, pos : pos + g.size].reshape((bits.shape[0], *g.shape, g.bits))
        pos += g.size
        vals = from_bits(chunk, g.dtype)
        out[g.name] = vals if batch else vals[0]
    return out


def evaluate(circuit: Circuit, values: Mapping[str, object], schedule: Schedule | None = None,
             batch: int | None = None) -> dict[str, np.ndarray]:
    """Evaluate a circuit in the clear on named, typed inputs."""
    from .schedule import schedule_circuit

    sched = schedule if schedule is not None else schedule_circuit(circuit)
    bits = evaluate_bits(sched, encode_inputs(circuit, values, batch))
    return decode_outputs(circuit, bits, batch=batch is not None)
