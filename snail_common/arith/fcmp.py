"""float32 comparisons, min/max, select, neg, abs.

Subnormal inputs compare as zeros of their sign and -0 == +0, as in numpy after
flushing. ``lt`` compares 32-bit keys on one carry chain: a float's key is its bits with
the 31 magnitude bits complemented when it is negative and the sign bit inverted, so
unsigned key order is float order (complementing reverses the order of negatives for
free). Two fixes make the flushed zeros equal: a zero-exponent x counts as positive (so
-0 and +0 share the key range just above the sign boundary), and its fraction is
ignored by forcing the chain's carry out of the fraction bits ("x's fraction is not
smaller"), which decides only when y is a zero too. 31 + 1 (sign) + 7 (exponent zero
test) + 2 = 41 AND gates, one over the 40 budget: a brute-force search over XOR-only
variants of the fixes (sign and complement choices from sx, sy and the zero test) found
none that is free. ``depth_opt`` uses (generate, propagate)
reduction trees instead of the chain (95 ANDs, 10 levels instead of 33).

NaN: a NaN compares like a number beyond infinity of its sign (so lt(1, +NaN) is 1 and
eq(NaN, NaN) is 1 for equal bit patterns) - unlike IEEE, where every NaN comparison is
false. Infinities compare normally.
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit import ONE, CircuitBuilder

from .fbits import fields, nonzero_exp
from .integer import carries, select
from .prefix import carry_out_tree
from .words import Word, and_all, bit, broadcast_lead, cat, wires


def lt(b: CircuitBuilder, x: Word, y: Word, depth_opt: bool = False) -> np.ndarray:
    """x < y (one wire per word)."""
    x, y = broadcast_lead(x, y)
    sx, ex, _ = fields(x)
    sy = y[..., 31]
    nzx = nonzero_exp(b, ex)
    nky = b.xor(y[..., :31], b.not_(sy)[..., None])       # complement of y's key
    carry = carry_out_tree if depth_opt else _ripple_carry
    # the fraction of a zero x is ignored anyway, so it can use the raw sign (no wait)
    kf = b.xor(x[..., :23], sx[..., None])
    c23 = b.or_(carry(b, kf, nky[..., :23], ONE), b.not_(nzx))
    sx = b.and_(sx, nzx)                                  # a zero x counts as +0
    ke = b.xor(x[..., 23:31], sx[..., None])
    ge_ = carry(b, cat(ke, bit(b.not_(sx))), cat(nky[..., 23:], bit(sy)), c23)
    return b.not_(ge_)


def le(b: CircuitBuilder, x: Word, y: Word, depth_opt: bool = False) -> np.ndarray:
    """x <= y, i.e. not (y < x)."""
    return b.not_(lt(b, y, x, depth_opt))


def gt(b: CircuitBuilder, x: Word, y: Word, depth_opt: bool = False) -> np.ndarray:
    return lt(b, y, x, depth_opt)


def ge(b: CircuitBuilder, x: Word, y: Word, depth_opt: bool = False) -> np.ndarray:
    return le(b, y, x, depth_opt)


def _ripple_carry(b: CircuitBuilder, x: Word, y: Word, cin) -> np.ndarray:
    return carries(b, x, y, cin)[..., -1]


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
