"""int32 <-> float32 conversions, and float32 -> narrow rounding.

``i2f``: absolute value (conditional negate), fused leading-zero normalization of the
32-bit magnitude, round to nearest even (ties are possible above 2^24).
``f2i``: rounds toward zero like a C cast; the 24-bit significand is shifted right from
the top of a 32-bit word by 157 - e. Out of range (|x| >= 2^31, except -2^31 itself),
infinities and NaN give INT32_MIN, the x86 'integer indefinite' value; zeros and
subnormals give 0.
``fround``: float32 -> a narrow format (fbits docstring), round to nearest even.
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit import CircuitBuilder

from .fbits import FRAC, check_frac, fields, nonzero_exp, pack, round_pack
from .integer import cond_negate, increment, sub
from .shift import normalize, shr
from .words import Word, and_all, cat, const, or_all, wires, zext


def i2f(b: CircuitBuilder, x: Word) -> Word:
    """Signed 32-bit integer word -> float32 word."""
    x = wires(x)
    s = x[..., 31]
    mag = cond_negate(b, x, s)              # -2^31 stays 0x80000000 = 2^31 unsigned
    v, lz = normalize(b, mag)
    sig, guard = v[..., 8:], v[..., 7]
    sticky = or_all(b, v[..., :7])
    e1 = sub(b, const(157, 10), zext(lz, 10))   # biased exponent 158 - lz, minus one
    return round_pack(b, s, e1, sig, guard, sticky, zero=b.not_(sig[..., 23]))


def f2i(b: CircuitBuilder, x: Word) -> Word:
    """float32 word -> signed 32-bit integer word (truncation)."""
    x = wires(x)
    s, e, f = fields(x)
    lead = x.shape[:-1]
    d = sub(b, const(157, 9), zext(e, 9))       # right shift of sig placed at bits 7..30
    over = d[..., 8]                            # e >= 158: out of range
    big = or_all(b, d[..., 5:8])                # shift >= 32: |x| < 1
    keep = b.and_(nonzero_exp(b, e), b.not_(b.or_(big, over)))
    sig = b.and_(cat(f, np.ones(lead + (1,), np.int32)), keep[..., None])
    word = cat(np.zeros(lead + (7,), np.int32), sig, np.zeros(lead + (1,), np.int32))
    mag = shr(b, word, d[..., :5])
    out = cond_negate(b, mag, s)
    out = np.array(out, copy=True)
    out[..., 31] = b.or_(out[..., 31], over)
    return out


def fround(b: CircuitBuilder, x: Word, frac: int) -> Word:
    """float32 -> the narrow format with ``frac`` fraction bits, round to nearest even
    (at most frac + 47 AND gates). Zeros and subnormals give signed zeros, rounding up
    from the largest binade gives an infinity; infinities and NaN are not rounded (a NaN
    keeps its top payload bits, which may leave an infinity)."""
    check_frac(frac)
    x = wires(x)
    if frac == FRAC:
        return x
    s, e, f = fields(x)
    drop = FRAC - frac
    keep = f[..., drop:]
    sticky = or_all(b, f[..., : drop - 1]) if drop > 1 else np.zeros_like(s)
    normal = nonzero_exp(b, e)
    live = b.and_(normal, b.not_(and_all(b, e)))            # finite and nonzero
    rnd = b.and_(b.and_(f[..., drop - 1], b.or_(sticky, keep[..., 0])), live)
    mant, carry = increment(b, keep, rnd)
    exp, _ = increment(b, e, carry)
    return pack(s, exp, b.and_(mant, normal[..., None]))
