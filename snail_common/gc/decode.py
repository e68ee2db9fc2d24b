"""Output decoding by the client, which is also where cheating is caught.

The evaluator returns one label per output wire; the garbler returns the zero-labels. A
label equal to L0 means 0, to L0 ^ D means 1. Anything else means the tables, the labels or
the evaluation were tampered with, and the whole result is rejected: the evaluator cannot
forge the other valid label without knowing D.
"""

from __future__ import annotations

import numpy as np

from .labels import check_delta


class IntegrityError(Exception):
    """An output label is neither L0 nor L0 ^ D: the garbled run cannot be trusted."""


def decode_output_labels(delta: np.ndarray | bytes, zero_labels: np.ndarray,
                         active_labels: np.ndarray) -> np.ndarray:
    """bool (n_outputs,) from the output zero-labels and the evaluator's active labels."""
    d = check_delta(delta)
    zero = np.asarray(zero_labels, dtype=np.uint64)
    active = np.asarray(active_labels, dtype=np.uint64)
    if zero.ndim != 2 or zero.shape[1] != 2 or zero.shape != active.shape:
        raise IntegrityError(f"expected two label arrays of shape (n, 2), got {zero.shape} "
                             f"and {active.shape}")
    diff = zero ^ active
    one = (diff == d).all(axis=1)
    bad = ~(one | (diff == 0).all(axis=1))
    if bad.any():
        where = np.flatnonzero(bad)
        raise IntegrityError(f"{where.size} of {len(bad)} output labels are invalid "
                             f"(first: output {where[0]})")
    return one
