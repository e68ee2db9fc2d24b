"""Public float32 constants as wire words (wires 0/1, so they cost nothing downstream)."""

from __future__ import annotations

import numpy as np

from snail_common.circuit import CircuitBuilder

from .words import Word, const


def fconst(value: float, shape: tuple[int, ...] = ()) -> Word:
    """The float32 rounding of ``value`` as a 32-wire constant word (broadcast to shape)."""
    bits = int(np.asarray(value, np.float32).view(np.uint32))
    return np.broadcast_to(const(bits, 32), tuple(shape) + (32,)).copy()


def fconst_like(b: CircuitBuilder, value: float, like: Word) -> Word:
    """A constant with the leading shape of ``like``."""
    return fconst(value, np.shape(like)[:-1])
