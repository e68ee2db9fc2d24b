"""float32 comparisons, min/max, select, neg, abs.

Subnormal inputs compare as zeros of their sign and -0 == +0, as in numpy after
flushing. ``lt`` runs one 31-bit carry chain on the magnitudes, XORed with the sign
when both are negative (complementing reverses unsigned order for free). A zero
exponent on x forces the mantissa part of the chain to "not less": it only matters
when the exponents tie, i.e. when both are zeros. With signs differing, x < y iff x is
negative and not both zero, and the same chain (uncomplemented) then yields [y != 0]
whenever x is zero: 31 + 7 + 4 = 42 AND gates.

NaN: a NaN compares like a number beyond infinity of its sign (so lt(1, +NaN) is 1 and
eq(NaN, NaN) is 1 for equal bit patterns) - unlike IEEE, where every NaN comparison is
false. Infinities compare normally.
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit import ONE, CircuitBuilder

from .fbits import fields, nonzero_exp
from .integer import carries, select
from .words import Word, and_all, broadcast_lead, wires


def lt(b: CircuitBuilder, x: Word, y: Word) -> np.ndarray:
    """x < y (one wire per word)."""
    x, y = broadcast_lead(x, y)
    sx, ex, _ = fields(x)
    sy = y[..., 31]
    t = sy[..., None]
    ax, ay = b.xor(x[..., :31], t), b.xor(y[..., :31], t)
    zx = b.not_(nonzero_exp(b, ex))
    c23 = carries(b, ax[..., :23], b.not_(ay[..., :23]), ONE)[..., -1]
    c23 = b.or_(c23, zx)
    ge_ = carries(b, ax[..., 23:], b.not_(ay[..., 23:]), c23)[..., -1]
    c = b.not_(ge_)
    differ = b.xor(sx, sy)
    return b.mux(differ, c, b.and_(sx, b.or_(c, b.not_(zx))))


def le(b: CircuitBuilder, x: Word, y: Word) -> np.ndarray:
    """x <= y, i.e. not (y < x)."""
    return b.not_(lt(b, y, x))


def gt(b: CircuitBuilder, x: Word, y: Word) -> np.ndarray:
    return lt(b, y, x)


def ge(b: CircuitBuilder, x: Word, y: Word) -> np.ndarray:
    return le(b, y, x)


def eq(b: CircuitBuilder, x: Word, y: Word) -> np.ndarray:
    """x == y: equal exponents and (both zero, or equal sign and fraction): 39 ANDs."""
    x, y = broadcast_lead(x, y)
    same = b.not_(b.xor(x, y))
    e_eq = and_all(b, same[..., 23:31])
    zx = b.not_(nonzero_exp(b, x[..., 23:31]))
    rest = and_all(b, np.concatenate([same[..., :23], same[..., 31:]], axis=-1))
    return b.and_(e_eq, b.or_(zx, rest))


def fselect(b: CircuitBuilder, cond, if0: Word, if1: Word) -> Word:
    """``if1`` where cond else ``if0``, bit for bit: 32 ANDs."""
    return select(b, cond, if0, if1)


def fmin(b: CircuitBuilder, x: Word, y: Word) -> Word:
    """y if y < x else x (ties, e.g. -0 vs +0, return x); one of the inputs unchanged."""
    x, y = broadcast_lead(x, y)
    return select(b, lt(b, y, x), x, y)


def fmax(b: CircuitBuilder, x: Word, y: Word) -> Word:
    """y if x < y else x."""
    x, y = broadcast_lead(x, y)
    return select(b, lt(b, x, y), x, y)


def fneg(b: CircuitBuilder, x: Word) -> Word:
    """-x: flips the sign wire (a free NOT)."""
    x = np.array(wires(x), copy=True)
    x[..., 31] = b.not_(x[..., 31])
    return x


def fabs(b: CircuitBuilder, x: Word) -> Word:
    """|x|: the sign wire becomes constant 0 (no gate)."""
    x = np.array(wires(x), copy=True)
    x[..., 31] = 0
    return x
