"""float32 multiplication, general and by a public constant.

The 24x24 significand product uses the odd-digit radix-4 multiplier (~720 AND gates);
hidden bits are the public constant 1 (a zero/subnormal operand flushes the result
anyway), the product's top bit picks a 1-bit normalization, the low 22 bits only feed
the sticky OR. Multiplying by a public constant replaces the product by one adder per
nonzero signed digit of the constant's significand, and by nothing for a power of two.

Special inputs (sign always sx ^ sy): a zero or subnormal operand gives a zero, an
infinite operand an infinity, inf * 0 a NaN (quiet, payload 0); a NaN operand acts as
an infinity. ``fmul_const`` treats an infinite or NaN x like a huge finite number (the
result is an infinity for |c| >= 1, and unspecified otherwise).
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit import ONE, CircuitBuilder

from .fbits import FRAC, check_frac, fields, nonzero_exp, round_pack
from .integer import add
from .multiply import mul, mul_const
from .words import Word, and_all, broadcast_lead, cat, const, or_all, zext


def _finish(b: CircuitBuilder, sign, e_sum: Word, prod: Word, p: int, zero,
            inf=None, nan=None) -> Word:
    """Normalize a product of two [1,2) significands (prod has 2p bits, value in [1, 4)
    times 2^(2p-2)) and round to a p-bit significand. ``e_sum`` = biased result exponent
    minus one before the normalization carry, as a signed 10-bit word."""
    top = prod.shape[-1]
    hi = prod[..., top - 1]
    sig = b.mux(hi[..., None], prod[..., top - p - 1 : top - 1], prod[..., top - p : top])
    guard = b.mux(hi, prod[..., top - p - 2], prod[..., top - p - 1])
    sticky = b.or_(or_all(b, prod[..., : top - p - 2]), b.and_(hi, prod[..., top - p - 2]))
    e1 = add(b, e_sum, np.zeros(10, np.int32), hi)
    return round_pack(b, sign, e1, sig, guard, sticky, zero=zero, inf=inf, nan=nan)


def fmul(b: CircuitBuilder, x: Word, y: Word, frac: int = FRAC) -> Word:
    """x * y as float32 words, or in the narrow format with ``frac`` fraction bits."""
    check_frac(frac)
    x, y = broadcast_lead(x, y)
    sx, ex, fx = fields(x, frac)
    sy, ey, fy = fields(y, frac)
    zero = b.not_(b.and_(nonzero_exp(b, ex), nonzero_exp(b, ey)))
    inf = b.or_(and_all(b, ex), and_all(b, ey))
    lead = x.shape[:-1]
    one = np.full(lead + (1,), ONE, np.int32)
    prod = mul(b, cat(fx, one), cat(fy, one))             # 2p bits, value in [1, 4) * 2^(2p-2)
    e_sum = add(b, add(b, zext(ex, 10), zext(ey, 10)), const(-128, 10))
    return _finish(b, b.xor(sx, sy), e_sum, prod, frac + 1, zero, inf, b.and_(inf, zero))


def fmul_const(b: CircuitBuilder, x: Word, c: float) -> Word:
    """x * c for a public finite float32 c: cheaper than fmul (no partial products)."""
    x = np.asarray(x, np.int32)
    cbits = int(np.asarray(c, np.float32).view(np.uint32))
    sc, ec, fc = cbits >> 31, (cbits >> 23) & 0xFF, cbits & 0x7FFFFF
    sx, ex, fx = fields(x)
    sign = b.xor(sx, ONE) if sc else sx
    if ec == 0xFF:
        raise ValueError("fmul_const needs a finite constant")
    if ec == 0:  # zero (or subnormal, flushed): a signed zero
        return cat(np.zeros(x.shape[:-1] + (31,), np.int32), sign[..., None])
    zero = b.not_(nonzero_exp(b, ex))
    mc = (1 << 23) | fc
    tz = (mc & -mc).bit_length() - 1
    mc_odd = mc >> tz                                     # c = mc_odd * 2^(tz-23) * 2^(ec-127)
    lead = x.shape[:-1]
    ma = cat(fx, np.full(lead + (1,), ONE, np.int32))
    e_sum = add(b, zext(ex, 10), const(ec - 128, 10))
    if mc_odd == 1:  # power of two: exponent arithmetic only
        return round_pack(b, sign, e_sum, ma, np.zeros(lead, np.int32), None, zero=zero)
    k = mc_odd.bit_length()                               # product of 24 x k bits
    prod = mul_const(b, ma, mc_odd, 24 + k)
    # pad so the binary point sits where _finish expects it (2 x 24-bit operands)
    prod = cat(np.zeros(lead + (24 - k,), np.int32), prod) if k < 24 else prod
    return _finish(b, sign, e_sum, prod, 24, zero)
