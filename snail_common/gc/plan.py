"""Executable form of a Schedule for the garbling engine, built once per schedule and cached.

A wide linear step whose outputs have different term counts would need ``reduceat``,
several times slower than dense gathers; the plan regroups its outputs by term count so
every group is a dense matrix stored column by column (one contiguous index array per
term). Small ragged steps keep ``reduceat``: there the number of numpy calls dominates. Both
garbler and evaluator run the same plan; the schedule's own arrays are used for AND steps.
"""

from __future__ import annotations

import weakref
from typing import NamedTuple

import numpy as np

from snail_common.circuit.schedule import AndStep, LinearStep, Schedule

from .slots import slot_view


class LinearGroup(NamedTuple):
    out: np.ndarray  # slots written
    columns: tuple[np.ndarray, ...]  # columns[k][i]: k-th term of output i


class LinearPlan(NamedTuple):
    groups: tuple[LinearGroup, ...]

    def run(self, labels: np.ndarray, slots: np.ndarray) -> None:
        """Apply in place. Every group is computed before any is written: outputs may
        reuse slots whose last read is this step."""
        take = labels.take
        results = []
        for g in self.groups:
            acc = take(g.columns[0], axis=0)
            for col in g.columns[1:]:
                acc ^= take(col, axis=0)
            results.append(acc)
        for g, acc in zip(self.groups, results):
            slots[g.out] = slot_view(acc)


class RaggedPlan(NamedTuple):
    """A small linear step with mixed term counts: one gather and one reduceat cost fewer
    numpy calls than a dense group per count."""

    out: np.ndarray
    terms: np.ndarray
    starts: np.ndarray

    def run(self, labels: np.ndarray, slots: np.ndarray) -> None:
        acc = np.bitwise_xor.reduceat(labels.take(self.terms, axis=0), self.starts, axis=0)
        slots[self.out] = slot_view(acc)


class AndPlan(NamedTuple):
    out: np.ndarray
    a: np.ndarray
    b: np.ndarray
    first: int  # global index of the step's first AND gate (its tweak base)


class Plan(NamedTuple):
    steps: tuple[AndPlan | LinearPlan | RaggedPlan, ...]


_cache: dict[int, Plan] = {}


def plan_for(schedule: Schedule) -> Plan:
    """The plan of ``schedule``, built on first use and kept while the schedule lives."""
    key = id(schedule)
    plan = _cache.get(key)
    if plan is None:
        plan = _cache[key] = _build(schedule)
        weakref.finalize(schedule, _cache.pop, key, None)
    return plan


def _build(schedule: Schedule) -> Plan:
    steps = []
    for i, step in enumerate(schedule.steps()):
        if isinstance(step, AndStep):
            steps.append(AndPlan(step.out, step.a, step.b, int(schedule.step_lo[i])))
        else:
            steps.append(_linear(step))
    return Plan(tuple(steps))


RAGGED_MAX_OUTPUTS = 64  # below this, per-call overhead outweighs reduceat's slowness


def _linear(step: LinearStep) -> LinearPlan | RaggedPlan:
    t, w = step.terms, step.width
    if w or not step.out.size:
        cols = tuple(np.ascontiguousarray(t[k::w]) for k in range(w)) if w else ()
        return LinearPlan((LinearGroup(step.out, cols),) if w else ())
    counts = np.diff(np.append(step.starts, len(t)))
    if np.any(counts == 0):
        raise ValueError("a linear step output has no terms")
    if len(step.out) <= RAGGED_MAX_OUTPUTS:
        return RaggedPlan(step.out, step.terms, step.starts)
    order = np.argsort(counts, kind="stable")
    groups = []
    for c in np.unique(counts).tolist():
        rows = order[counts[order] == c]
        first = step.starts[rows]
        groups.append(LinearGroup(step.out[rows],
                                  tuple(t[first + k] for k in range(c))))
    return LinearPlan(tuple(groups))
