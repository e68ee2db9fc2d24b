"""A plan as three flat arrays, so a cached circuit's plan is loaded, not rebuilt.

Building the engine plan of the n = 256 localization circuit takes 3-4 s (run finding
over 200 M slot indices), longer than the first invocation's garbling. The plan is a
pure function of the schedule and of the plan code's version, so it is stored next to
the schedule in the cache entry: a token array (structure, slices, offsets) and two
index pools (int32 slot lists, intp ``reduceat`` operands). Decoding makes a few Python
objects per piece and views into the pools (memory-mapped by the cache): no copies.

Tokens, depth first: a plan is ``n_steps, max_and_step`` then its steps; an AND piece
``0, first, n, direct, rows(out), rows(a), rows(b)``; a linear step ``1, direct,
n_groups`` then groups: ``0|1, rows(out), k, k rows`` (run or gathered columns) or ``2,
rows(out), rows(terms), rows(starts)`` (ragged). Rows are ``0, start, stop, step`` (a
slice; step -1 for a broadcast), or ``1|2, offset, length`` (a list in pool 32 or 64).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .plan import AndPlan, LinearGroup, LinearPlan, Plan, RaggedGroup, RunGroup
from .slots import Rows

FORMAT = 1
_GROUPS = (RunGroup, LinearGroup, RaggedGroup)


class StoredPlan(NamedTuple):
    tokens: np.ndarray  # int64
    pool32: np.ndarray  # int32
    pool64: np.ndarray  # int64


def encode(plan: Plan) -> StoredPlan:
    """The plan as flat arrays (see the module docstring)."""
    tokens: list[int] = [len(plan.steps), plan.max_and_step]
    pools: dict[int, list[np.ndarray]] = {1: [], 2: []}
    sizes = {1: 0, 2: 0}

    def rows(r: Rows) -> None:
        if isinstance(r, slice):
            tokens.extend((0, r.start, r.stop, -1 if r.step is None else r.step))
            return
        if r.dtype not in (np.int32, np.int64):
            raise ValueError(f"plan index lists are int32 or int64, got {r.dtype}")
        pool = 2 if r.dtype == np.int64 else 1
        tokens.extend((pool, sizes[pool], len(r)))
        pools[pool].append(r)
        sizes[pool] += len(r)

    for step in plan.steps:
        if isinstance(step, AndPlan):
            tokens.extend((0, step.first, step.n, int(step.direct)))
            for r in (step.out, step.a, step.b):
                rows(r)
            continue
        tokens.extend((1, int(step.direct), len(step.groups)))
        for g in step.groups:
            tokens.append(_GROUPS.index(type(g)))
            rows(g.out)
            if isinstance(g, RaggedGroup):
                rows(g.terms)
                rows(g.starts)
            else:
                tokens.append(len(g.columns))
                for col in g.columns:
                    rows(col)

    def pool(kind: int, dtype: type) -> np.ndarray:
        parts = pools[kind]
        return np.concatenate(parts).astype(dtype, copy=False) if parts else np.empty(0, dtype)

    return StoredPlan(np.array(tokens, np.int64), pool(1, np.int32), pool(2, np.int64))


def decode(stored: StoredPlan) -> Plan:
    """The plan ``encode`` was given, its index lists views into the pools."""
    tokens = stored.tokens.tolist()
    pools = {1: np.asarray(stored.pool32), 2: np.asarray(stored.pool64)}  # no memmap
    # subclass: its slices pay a Python hook each
    pos = 0

    def take(n: int) -> list[int]:
        nonlocal pos
        pos += n
        return tokens[pos - n : pos]

    def rows() -> Rows:
        (kind,) = take(1)
        if kind == 0:
            start, stop, step = take(3)
            return slice(start, stop, None if step == -1 else step)
        offset, n = take(2)
        return pools[kind][offset : offset + n]

    n_steps, widest = take(2)
    steps: list[AndPlan | LinearPlan] = []
    for _ in range(n_steps):
        kind, a, b = take(3)
        if kind == 0:
            (direct,) = take(1)
            steps.append(AndPlan(rows(), rows(), rows(), a, b, bool(direct)))
            continue
        groups = []
        for _ in range(b):
            (group,) = take(1)
            out = rows()
            if group == 2:
                groups.append(RaggedGroup(out, rows(), rows()))
            else:
                (k,) = take(1)
                groups.append(_GROUPS[group](out, tuple(rows() for _ in range(k))))
        steps.append(LinearPlan(tuple(groups), bool(a)))
    if pos != len(tokens):
        raise ValueError(f"stored plan has {len(tokens) - pos} tokens left over")
    return Plan(tuple(steps), widest)
