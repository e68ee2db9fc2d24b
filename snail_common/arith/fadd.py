"""float32 addition and subtraction (round to nearest even, flush to zero).

Data path (one comparator, one alignment shifter, one normalizing shifter):
1. |x| < |y| on the 31 magnitude bits picks the larger operand a; the smaller is
   b = x ^ y ^ a for free, so the swap costs one mux per bit.
2. The exponent difference d = ea - eb aligns b's significand to a 26-bit window
   (24 bits + guard + round) plus a sticky bit; d >= 32 or a zero b shift everything out.
3. One 26-bit add/subtract (the choice is an XOR and a carry in). The sticky bit is not
   an adder bit: subtracting a lost fraction f > 0 just drops the carry in, since
   a - B - f = (a + ~B) + (1 - f).
4. A fused leading-zero/shift stage normalizes the 27-bit result (carry on top). Only
   effective subtraction with d <= 1 ("near" case) can shift by 3 or more, and there the
   round bit and sticky are zero: the big stages skip them, and the final sticky comes
   from the two low bits and the top two bits (the shift being 0, 1 or 2).
5. round_pack rounds to nearest even, flushes tiny results and saturates to infinity.

AND gates (528): compare 31, swap 32, hidden bits 14, d 7, saturation 6, alignment
shifter 129 + its sticky 32 (+1 zero-b mask), adder 26 + 1, normalization 154 (zero tests
26, muxes 123, sticky 5), exponent 8, sign 3, infinity test 7, rounding and packing 77
(increment 23, exponent update 9, overflow 9, flush/saturate masks 31, rest 5).

Why not one shifter for both roles (far path: align by d > 1; near path: normalize)?
The near path must subtract before shifting and the far path after, so it needs a
second 25-bit subtractor, a mux into the shifter, a mux after it and a separate 2-stage
normalizer for the far path (0/1/2): about 150 gates. Sharing the OR trees (the near
leading-zero tests are the far sticky ORs) saves about 25 and the shifter about 125,
so the estimate lands within a few gates of this design, not near 400.

``depth_opt=True`` swaps every carry chain (comparator, exponent difference, adder,
exponent update, rounding increment) for a log-depth one: 61 AND levels instead of 133
for 740 AND gates.

Special inputs: zero and subnormal operands act as signed zeros ((+0) + (-0) = +0,
x - x = +0). An infinite operand gives an infinity with the sign of the operand of
larger magnitude; inf - inf gives an infinity too (sign of x), not NaN, and a NaN
operand behaves like an infinity (NaN inputs do not propagate).
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit import ONE, ZERO, CircuitBuilder

from .fbits import FRAC, check_frac, round_pack
from .integer import add, add_carry, carries, select
from .prefix import add_fast, carry_out_tree, prefix_carries
from .shift import shl_const, shr_sticky
from .words import Word, and_all, bit, broadcast_lead, cat, or_all, sext, zext

NEAR_ONLY = 4  # normalization stages of 4 and more: only the near case takes them


def fadd(b: CircuitBuilder, x: Word, y: Word, depth_opt: bool = False,
         frac: int = FRAC) -> Word:
    """x + y as float32 words, or in the narrow format with ``frac`` fraction bits."""
    check_frac(frac)
    x, y = broadcast_lead(x, y)
    lead = x.shape[:-1]
    p = frac + 1                                              # significand bits
    sx, sy = x[..., 31], y[..., 31]
    mx, my = x[..., FRAC - frac : 31], y[..., FRAC - frac : 31]
    swap = b.not_(_carry_out(b, mx, b.not_(my), ONE, depth_opt))      # |x| < |y|
    ma = select(b, swap, mx, my)
    mb = b.xor(b.xor(mx, my), ma)
    sa = b.mux(swap, sx, sy)
    eff_sub = b.xor(sx, sy)
    ea, eb = ma[..., frac:], mb[..., frac:]
    ha, hb = or_all(b, ea), or_all(b, eb)
    d = (add_fast if depth_opt else add)(b, ea, b.not_(eb), ONE)      # 0 <= d <= 255
    # the window holds p + 2 bits: d >= 2^stages or b == 0 forces the top stages on,
    # a shift of at least p + 2 (past the whole window)
    stages = (p + 2).bit_length()
    forced = max(j for j in range(stages) if (1 << stages) - (1 << j) >= p + 2)
    big = b.or_(or_all(b, d[..., stages:]), b.not_(hb))
    amount = cat(d[..., :forced], b.or_(d[..., forced:stages], big[..., None]))
    zero2 = np.zeros(lead + (2,), np.int32)
    win = cat(zero2, mb[..., :frac], bit(hb))                # [round, guard, p-bit sig]
    aligned, st = shr_sticky(b, win, amount, order="small")
    st = b.and_(st, hb)
    wa = cat(zero2, ma[..., :frac], bit(ha))                   # [round, guard, sig]
    wb = b.xor(aligned, eff_sub[..., None])
    # subtracting the lost fraction f > 0 borrows one: a - B - f = (a + ~B) + (1 - f)
    s, cout = _add_carry(b, wa, wb, b.and_(eff_sub, b.not_(st)), depth_opt)
    v = cat(s, bit(b.xor(cout, eff_sub)))
    top, shift, sticky = _normalize(b, v, st)
    sig, guard = top[..., 1:], top[..., 0]
    # biased exponent - 1 = ea - shift; 9 bits hold [-31, 255], the 10th is a sign copy
    e1 = sext((add_fast if depth_opt else add)(b, zext(ea, 9), b.not_(zext(shift, 9)), ONE), 10)
    cancel = b.not_(sig[..., p - 1])
    sign = b.mux(ha, b.and_(sx, sy), b.and_(sa, b.not_(cancel)))
    return round_pack(b, sign, e1, sig, guard, sticky, zero=cancel, inf=and_all(b, ea),
                      exact_tiny=True, depth_opt=depth_opt)


def fsub(b: CircuitBuilder, x: Word, y: Word, depth_opt: bool = False,
         frac: int = FRAC) -> Word:
    """x - y: addition with y's sign flipped (free)."""
    y = np.array(y, np.int32, copy=True)
    y[..., 31] = b.not_(y[..., 31])
    return fadd(b, x, y, depth_opt, frac)


def _carry_out(b: CircuitBuilder, x: Word, y: Word, cin, fast: bool) -> np.ndarray:
    return carry_out_tree(b, x, y, cin) if fast else carries(b, x, y, cin)[..., -1]


def _add_carry(b: CircuitBuilder, x: Word, y: Word, cin, fast: bool):
    if not fast:
        return add_carry(b, x, y, cin)
    c = prefix_carries(b, x, y, cin)
    return b.xor(b.xor(x, y), c[..., :-1]), c[..., -1]


def _normalize(b: CircuitBuilder, v: Word, st) -> tuple[Word, Word, np.ndarray]:
    """Shift the adder result left until its top bit is 1.

    ``v`` is [round, guard, p-bit significand, carry]; ``st`` says the alignment lost
    nonzero bits below the round bit. Returns (guard + p-bit significand after the
    shift, the shift amount word, the sticky OR of everything below the guard). Stage
    2^j shifts when the top 2^j bits are zero; a nonzero v has a 1 at the guard or above
    (the round bit only with no cancellation), so the stages cover shifts up to n - 2.
    A shift of 3 or more only happens in the near case, where the round bit and ``st``
    are zero: the stages of NEAR_ONLY leave bit 0 alone, and a bit that is zero whenever
    the stage shifts and receives a zero keeps its wire for free. The sticky bit
    therefore needs only the shift-0/1/2 cases: ``st`` always, the round bit when the
    shift is <= 1 (one of the top two bits set), the guard bit when it is 0 (the top bit
    set).
    """
    n = v.shape[-1]
    sticky = b.or_(st, b.or_(b.and_(v[..., 0], b.or_(v[..., n - 2], v[..., n - 1])),
                             b.and_(v[..., 1], v[..., n - 1])))
    x = v
    amt = []
    for k in (1 << j for j in reversed(range((n - 2).bit_length()))):
        z = b.not_(or_all(b, x[..., n - k:]))
        amt.append(z)
        src = shl_const(x, k)
        known0 = np.zeros(n, bool)          # positions that are 0 whenever z is 1
        known0[n - k:] = True
        if k >= NEAR_ONLY:
            known0[:1] = True
        src_known0 = np.concatenate([np.ones(k, bool), known0[: n - k]])
        lowest = {2: 1, 1: 2}.get(k, 0)      # outputs below this are never read again
        change = ~(known0 & src_known0)
        change[:lowest] = False
        out = x.copy()
        out[..., change] = b.mux(z[..., None], x[..., change], src[..., change])
        x = out
    return x[..., 2:], np.stack(amt[::-1], axis=-1), sticky


__all__ = ["ZERO", "fadd", "fsub"]
