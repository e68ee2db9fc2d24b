"""Label storage: one ``(n_slots, 2)`` uint64 array per run, scattered into through its
16-byte void view, which numpy copies as single items (2-D row scatters are several times
slower)."""

from __future__ import annotations

import numpy as np

VOID16 = np.dtype("V16")


def slot_view(labels: np.ndarray) -> np.ndarray:
    """1-D view of a C-contiguous (n, 2) uint64 label array, one 16-byte item per label."""
    return labels.view(VOID16).reshape(-1)
