"""Arithmetic runs in a step's slot columns: the rows an executor can read and write as
strided views instead of gathers and scatters.

Random gathers over a slot array larger than the cache cost ~10 ns each; the scheduler
lays slots out so that most rows of a wide step advance every slot column by a constant
stride. A run is a maximal range of at least ``MIN_RUN`` such rows in which the output
column ascends (stride >= 1) and every operand column ascends or stays put (stride 0: one
slot read by every row, a broadcast view).
"""

from __future__ import annotations

import numpy as np

MIN_RUN = 128  # shorter runs cost more in numpy calls than their gathers do


def find_runs(out: np.ndarray, operands: list[np.ndarray], strided: bool,
              min_run: int = MIN_RUN) -> tuple[list[tuple[int, int]], np.ndarray]:
    """Row ranges [r0, r1) of runs of at least ``min_run`` rows (see the module
    docstring), and the rows outside them. Without ``strided``, only runs where every
    column advances by exactly one slot."""
    n = len(out)
    if n < max(min_run, 3):
        return [], np.arange(n)
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
    keep = last - first >= min_run
    first, last = first[keep], last[keep]
    strides = [c[first + 1].astype(np.int64) - c[first] for c in cols]
    keep = strides[0] >= 1
    for s in strides[1:]:
        keep &= s >= 0
    if not strided:
        for s in strides:
            keep &= s == 1
    first, last = first[keep], last[keep]
    covered = np.zeros(n + 1, np.int32)
    np.add.at(covered, first, 1)
    np.add.at(covered, last, -1)
    rest = np.flatnonzero(np.cumsum(covered[:n]) == 0)
    return list(zip(first.tolist(), last.tolist())), rest


def _stride(column: np.ndarray, r0: int) -> int:
    return int(column[r0 + 1]) - int(column[r0])


def run_slice(column: np.ndarray, r0: int, r1: int) -> slice:
    """Rows r0 .. r1-1 of a run's column as a slice of the slot axis; a column that stays
    on one slot is ``slice(s, s + 1)`` with no step, which broadcasts (see slots.part)."""
    start, stride = int(column[r0]), _stride(column, r0)
    if stride == 0:
        return slice(start, start + 1)
    return slice(start, start + stride * (r1 - r0 - 1) + 1, stride)
