"""Label storage: one ``(n_slots, 2)`` uint64 array per run, and the rows a step names in it.

A step names its slots either as one contiguous range (a ``slice``: reads are views or
memcpy, writes are memcpy) or as an index array (gathers, and scatters through the 16-byte
void view, which numpy copies as single items: 2-D row scatters are several times slower).
The schedule's slot allocator makes most outputs and many operands contiguous.
"""

from __future__ import annotations

import numpy as np

VOID16 = np.dtype("V16")

Rows = slice | np.ndarray


def slot_view(labels: np.ndarray) -> np.ndarray:
    """1-D view of a C-contiguous (n, 2) uint64 label array, one 16-byte item per label."""
    return labels.view(VOID16).reshape(-1)


def as_rows(idx: np.ndarray) -> Rows:
    """``idx`` as a slice when it is an ascending run of consecutive slots."""
    n = len(idx)
    if n and int(idx[-1]) - int(idx[0]) == n - 1 and (n == 1 or np.all(np.diff(idx) == 1)):
        return slice(int(idx[0]), int(idx[0]) + n)
    return idx


def part(rows: Rows, k: int, m: int) -> Rows:
    """Rows k .. k+m-1 of ``rows``."""
    if isinstance(rows, slice):
        return slice(rows.start + k, rows.start + k + m)
    return rows[k : k + m]


def gather_into(labels: np.ndarray, rows: Rows, out: np.ndarray) -> None:
    """out[i] = labels[rows[i]]; indices are trusted (the schedule made them)."""
    if isinstance(rows, slice):
        np.copyto(out, labels[rows])
    else:
        labels.take(rows, axis=0, out=out, mode="clip")


def gather(labels: np.ndarray, rows: Rows, scratch: np.ndarray) -> np.ndarray:
    """labels[rows], as a view when contiguous, else gathered into ``scratch[:len]``."""
    if isinstance(rows, slice):
        return labels[rows]
    out = scratch[: len(rows)]
    labels.take(rows, axis=0, out=out, mode="clip")
    return out


def write(labels: np.ndarray, slots: np.ndarray, rows: Rows, values: np.ndarray) -> None:
    """labels[rows] = values (a memcpy for a range, else a scatter into ``slots``, the
    slot_view of ``labels``)."""
    if isinstance(rows, slice):
        labels[rows] = values
    else:
        slots[rows] = slot_view(values)
