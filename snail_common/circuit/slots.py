"""Slot storage: one ``(n_slots, W)`` uint64 array per run, and the rows a step names in it.

A row is a wire's value: W words (a garbled label is W = 2; a cleartext run packs 64
input vectors per word). A step names its slots as an arithmetic run (a ``slice`` with a
positive step: reads are views, writes are strided copies), as one slot read by every
row (a ``slice`` without a step: a broadcast view), or as an index array (gathers, and
scatters through a void view of whole rows, which numpy copies as single items: 2-D row
scatters are several times slower). The schedule's slot allocator makes most outputs and
many operands runs. Strided views pay off only for single-word rows: numpy cannot merge
the axes of an (n, 2) view whose rows are not adjacent and loops two words at a time,
slower than a gather, so wider rows use only runs of adjacent slots.
"""

from __future__ import annotations

import numpy as np

Rows = slice | np.ndarray

MIN_STRIDED = 4  # shorter constant-stride lists stay index arrays (a view buys nothing)


def slot_view(labels: np.ndarray) -> np.ndarray:
    """1-D view of a C-contiguous (n, W) uint64 array, one W*8-byte item per row."""
    return labels.view(np.dtype(f"V{8 * labels.shape[1]}")).reshape(-1)


def as_rows(idx: np.ndarray, strided: bool = False) -> Rows:
    """``idx`` as a slice when it is an ascending run of consecutive slots (with
    ``strided``, of any step >= 1), else as a contiguous index array (``take`` copies a
    strided one on every call: 5-10 % of a wide evaluation)."""
    n = len(idx)
    if not n:
        return idx
    first = int(idx[0])
    if n == 1:
        return slice(first, first + 1, 1)
    stride = int(idx[1]) - first
    if stride < 1 or (stride > 1 and (not strided or n < MIN_STRIDED)):
        return np.ascontiguousarray(idx)
    if int(idx[-1]) - first != stride * (n - 1) or not np.all(np.diff(idx) == stride):
        return np.ascontiguousarray(idx)
    return slice(first, first + stride * (n - 1) + 1, stride)


def length(rows: Rows) -> int:
    """Number of rows named by an output (never a broadcast)."""
    if isinstance(rows, slice):
        return len(range(rows.start, rows.stop, rows.step))
    return len(rows)


def part(rows: Rows, k: int, m: int) -> Rows:
    """Rows k .. k+m-1 of ``rows``."""
    if isinstance(rows, slice):
        if rows.step is None:  # a broadcast: the same slot for every row
            return rows
        start = rows.start + k * rows.step
        return slice(start, start + (m - 1) * rows.step + 1, rows.step)
    return rows[k : k + m]


def gather_into(labels: np.ndarray, rows: Rows, out: np.ndarray) -> None:
    """out[i] = labels[rows[i]]; indices are trusted (the schedule made them)."""
    if isinstance(rows, slice):
        np.copyto(out, labels[rows])
    else:
        labels.take(rows, axis=0, out=out, mode="clip")


def gather(labels: np.ndarray, rows: Rows, scratch: np.ndarray) -> np.ndarray:
    """labels[rows], as a view when ``rows`` is a run, else gathered into ``scratch``."""
    if isinstance(rows, slice):
        return labels[rows]
    out = scratch[: len(rows)]
    labels.take(rows, axis=0, out=out, mode="clip")
    return out


def write(labels: np.ndarray, slots: np.ndarray, rows: Rows, values: np.ndarray) -> None:
    """labels[rows] = values (a copy for a run, else a scatter into ``slots``, the
    slot_view of ``labels``)."""
    if isinstance(rows, slice):
        labels[rows] = values
    else:
        slots[rows] = slot_view(values)
