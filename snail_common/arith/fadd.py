"""float32 addition and subtraction (round to nearest even, flush to zero).

Data path (one comparator, one alignment shifter, one normalizing shifter):
1. |x| < |y| on the 31 magnitude bits picks the larger operand a; the smaller is
   b = x ^ y ^ a for free, so the swap costs one mux per bit.
2. The exponent difference d = ea - eb aligns b's significand to a 26-bit window
   (24 bits + guard + round) plus a sticky bit; d >= 32 or a zero b shift everything out.
3. One 27-bit add/subtract (the choice is an XOR and a carry in).
4. A fused leading-zero/shift stage normalizes the 28-bit result (carry included).
5. round_pack rounds to nearest even, flushes tiny results and saturates to infinity.

Special inputs: zero and subnormal operands act as signed zeros ((+0) + (-0) = +0,
x - x = +0). An infinite operand gives an infinity with the sign of the operand of
larger magnitude; inf - inf gives an infinity too (sign of x), not NaN, and a NaN
operand behaves like an infinity (NaN inputs do not propagate).
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit import ZERO, CircuitBuilder

from .fbits import round_pack
from .integer import add_carry, lt, select, sub
from .shift import normalize, shr_sticky
from .words import Word, and_all, bit, broadcast_lead, cat, or_all, zext


def fadd(b: CircuitBuilder, x: Word, y: Word) -> Word:
    """x + y as float32 words."""
    x, y = broadcast_lead(x, y)
    lead = x.shape[:-1]
    sx, sy = x[..., 31], y[..., 31]
    mx, my = x[..., :31], y[..., :31]
    swap = lt(b, mx, my)
    ma = select(b, swap, mx, my)
    mb = b.xor(b.xor(mx, my), ma)
    sa = b.mux(swap, sx, sy)
    eff_sub = b.xor(sx, sy)
    ea, eb = ma[..., 23:31], mb[..., 23:31]
    ha, hb = or_all(b, ea), or_all(b, eb)
    d = sub(b, ea, eb)                                  # 0 <= d <= 255
    big = b.or_(or_all(b, d[..., 5:]), b.not_(hb))
    amount = b.or_(d[..., :5], big[..., None])          # saturate at 31
    zero2 = np.zeros(lead + (2,), np.int32)
    win = cat(zero2, mb[..., :23], bit(hb))                  # [round, guard, 24-bit sig]
    aligned, st = shr_sticky(b, win, amount, order="small")
    st = b.and_(st, hb)
    wa = cat(np.zeros(lead + (3,), np.int32), ma[..., :23], bit(ha))   # [st, r, g, sig]
    wb = cat(bit(st), aligned)
    s, cout = add_carry(b, wa, b.xor(wb, eff_sub[..., None]), eff_sub)
    v = cat(s, bit(b.xor(cout, eff_sub)))                    # 28 bits, carry on top
    v, shift = normalize(b, v)
    sig, guard = v[..., 4:], v[..., 3]
    sticky = or_all(b, v[..., :3])
    e1 = sub(b, zext(ea, 10), zext(shift, 10))          # biased exponent - 1
    cancel = b.not_(sig[..., 23])
    sign = b.mux(ha, b.and_(sx, sy), b.and_(sa, b.not_(cancel)))
    return round_pack(b, sign, e1, sig, guard, sticky, zero=cancel, inf=and_all(b, ea),
                      exact_tiny=True)


def fsub(b: CircuitBuilder, x: Word, y: Word) -> Word:
    """x - y: addition with y's sign flipped (free)."""
    y = np.array(y, np.int32, copy=True)
    y[..., 31] = b.not_(y[..., 31])
    return fadd(b, x, y)


__all__ = ["ZERO", "fadd", "fsub"]
