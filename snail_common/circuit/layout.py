"""Slot layout: the order of a step's rows and the slot of every scheduled wire.

Walking steps backwards, rows that die at the same step are put together in the order
their last reader reads them; each such run then gets one contiguous block of slots (best
fit among blocks freed before the step), so executors see long runs of equally spaced
slots (see schedule.py).
"""

from __future__ import annotations

from itertools import pairwise

import numpy as np

from .fold import AND_STEP, FoldedPlan
from .ir import FIRST_INPUT, Circuit


def order_rows(c: Circuit, plan: FoldedPlan) -> np.ndarray:
    """Reorder the rows of every step in place, walking steps backwards, and return each
    wire's death: the step of its last read (-1: never read; ``len(plan.kind)``: output).

    A step's rows are sorted by (term count, death, position of the last read), where a
    step's reads are numbered column by column (AND: every ``a`` then every ``b``; linear:
    per term count, term 0 of every row, then term 1, ...). Wires that die together then
    sit next to each other in the order their last reader reads them, so one contiguous
    block of slots holds them and that reader sees runs of consecutive slots.
    """
    S = len(plan.kind)
    if 256 * (S + 1) >= 2**32:
        raise ValueError(f"schedule has {S} steps: too many for the row sort key")
    death = np.full(c.n_wires, -1, np.int32)
    pos = np.zeros(c.n_wires, np.int32)
    outs = c.outputs
    death[outs] = S
    pos[outs[::-1]] = np.arange(outs.size, dtype=np.int32)[::-1]
    for t in range(S - 1, -1, -1):
        lo, hi = int(plan.lo[t]), int(plan.hi[t])
        if plan.kind[t] == AND_STEP:
            order = _row_order(plan.and_out[lo:hi], death, pos, t)
            for arr in (plan.and_out, plan.and_a, plan.and_b):
                arr[lo:hi] = arr[lo:hi][order]
            reads = np.concatenate([plan.and_a[lo:hi], plan.and_b[lo:hi]])
        else:
            reads = _order_linear(plan, lo, hi, death, pos, t)
        idx = np.flatnonzero(death[reads] < 0).astype(np.int32)
        new = reads[idx]
        pos[new[::-1]] = idx[::-1]  # position of (one of) its reads here
        death[new] = t
    return death


def _row_order(out: np.ndarray, death: np.ndarray, pos: np.ndarray, t: int,
               lens: np.ndarray | None = None, n_steps: int = 0) -> np.ndarray:
    """Row permutation of step t: by (term count,) death, last-read position; rows never
    read keep their order and die at t. One int64 key: death <= n_steps, term count
    < 256 and position < 2**31. Keys are distinct (a read position holds one wire; rows
    read later die after t), so an unstable sort (SIMD quicksort, twice as fast) gives
    the same order."""
    d = death[out].astype(np.int64)
    unread = d < 0
    d[unread] = t
    if lens is not None:
        d += lens.astype(np.int64) * (n_steps + 1)
    p = pos[out]
    p[unread] = np.flatnonzero(unread)
    d <<= 31
    d |= p
    return np.argsort(d)


def _order_linear(plan: FoldedPlan, lo: int, hi: int, death: np.ndarray, pos: np.ndarray,
                  t: int) -> np.ndarray:
    """Reorder the rows of linear step t (CSR terms move with them); returns its reads
    numbered column by column within each term count."""
    terms = plan.terms_of(t)
    lens = plan.lin_lens[lo:hi].astype(np.int64)
    order = _row_order(plan.lin_out[lo:hi], death, pos, t, lens, len(plan.kind))
    plan.lin_out[lo:hi] = plan.lin_out[lo:hi][order]
    old_start = (np.cumsum(lens) - lens)[order]
    lens = lens[order]
    plan.lin_lens[lo:hi] = lens
    ends = np.cumsum(lens)
    idx = np.repeat(old_start - ends + lens, lens) + np.arange(terms.size)
    terms[:] = terms[idx]
    cuts = np.flatnonzero(lens[1:] != lens[:-1]) + 1
    bounds = np.concatenate([[0], cuts, [hi - lo]])
    cols = [terms[ends[r0] - lens[r0] : ends[r1 - 1]].reshape(r1 - r0, lens[r0]).T.ravel()
            for r0, r1 in pairwise(bounds.tolist())]
    return np.concatenate(cols)


class _FreeSpace:
    """Free slot extents (sorted, coalesced): best-fit allocation of contiguous blocks."""

    def __init__(self, n_slots: int) -> None:
        self.start = np.zeros(0, np.int64)
        self.size = np.zeros(0, np.int64)
        self.n_slots = n_slots

    def release(self, start: np.ndarray, size: np.ndarray) -> None:
        if not start.size:
            return
        start = np.concatenate([self.start, start])
        size = np.concatenate([self.size, size])
        keep = size > 0
        start, size = start[keep], size[keep]
        order = np.argsort(start, kind="stable")
        start, size = start[order], size[order]
        if start.size:
            first = np.concatenate([[True], start[1:] != start[:-1] + size[:-1]])
            heads = np.flatnonzero(first)
            start, size = start[heads], np.add.reduceat(size, heads)
        self.start, self.size = start, size

    def take(self, n: int) -> int:
        """First slot of a free block of n slots; grows the slot space when none fits."""
        fits = np.flatnonzero(self.size >= n)
        if fits.size:
            i = fits[np.argmin(self.size[fits])]
            s = int(self.start[i])
            self.start[i] += n
            self.size[i] -= n
            return s
        s = self.n_slots
        if self.size.size and self.start[-1] + self.size[-1] == s:
            s = int(self.start[-1])
            self.start, self.size = self.start[:-1], self.size[:-1]
        self.n_slots = s + n
        return s


def allocate_slots(c: Circuit, plan: FoldedPlan, death: np.ndarray,
                    reuse: bool) -> tuple[np.ndarray, int]:
    """Map every scheduled wire to a slot; returns (slot_of over wire ids, n_slots).

    Each run of a step's rows that die at the same step gets one contiguous block, taken
    from slots freed before the step (never from slots the step itself reads, so an
    executor may write outputs as it goes). A block is freed after its death step.
    """
    F, S = FIRST_INPUT + c.n_inputs, len(plan.kind)
    slot_of = np.full(c.n_wires, -1, np.int32)
    slot_of[:F] = np.arange(F, dtype=np.int32)
    space = _FreeSpace(F)
    freed: list[list[tuple[int, int]]] = [[] for _ in range(S + 1)]
    # inputs and constants: runs of equal death, released after that step
    d_in = death[:F]
    cuts = np.concatenate([[0], np.flatnonzero(d_in[1:] != d_in[:-1]) + 1, [F]])
    run_d = d_in[cuts[:-1]]
    mortal = run_d < S
    in_start, in_size, in_when = cuts[:-1][mortal], np.diff(cuts)[mortal], run_d[mortal] + 1
    for s in range(S):
        lo, hi = int(plan.lo[s]), int(plan.hi[s])
        out = (plan.and_out if plan.kind[s] == AND_STEP else plan.lin_out)[lo:hi]
        if reuse:
            now = in_when == s
            blocks = np.array(freed[s], np.int64).reshape(-1, 2)
            freed[s] = []
            space.release(np.concatenate([in_start[now], blocks[:, 0]]),
                          np.concatenate([in_size[now], blocks[:, 1]]))
        d = death[out]
        d[d < 0] = s
        cuts = np.concatenate([[0], np.flatnonzero(d[1:] != d[:-1]) + 1, [out.size]])
        for r0, r1 in zip(cuts[:-1].tolist(), cuts[1:].tolist()):
            first = space.take(r1 - r0)
            slot_of[out[r0:r1]] = np.arange(first, first + r1 - r0, dtype=np.int32)
            if d[r0] < S:
                freed[d[r0] + 1].append((first, r1 - r0))
    return slot_of, space.n_slots


def to_slots(slot_of: np.ndarray, arr: np.ndarray, chunk: int = 1 << 22) -> None:
    """``slot_of[arr]`` written over arr, a chunk at a time (no full-size temporaries)."""
    for i in range(0, arr.size, chunk):
        arr[i : i + chunk] = slot_of[arr[i : i + chunk]]
