"""float32 square root by the non-restoring digit-by-digit method.

Each root bit is one add-or-subtract of (4Q+1) / (4Q+3) into a remainder that grows by
one bit per step, so the 25 root bits cost about sum(k + 3) AND gates. As in division,
no remainder test is needed: a root of a 24-bit significand is never exactly halfway.
The exponent's parity picks how the significand's bits pair up (one mux per bit), and
the result exponent is floor((e + 127) / 2).

``depth_opt=True`` uses log-depth adders in the iterations.

Special inputs: sqrt(+-0) = +-0 (subnormals count as zeros), a negative number gives a
NaN (0x7FC00000 with the sign bit set), +inf gives +inf, a NaN input gives +-inf or NaN.
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit import ONE, ZERO, CircuitBuilder

from .fbits import fields, nonzero_exp, round_pack
from .integer import add
from .prefix import add_fast
from .shift import shr_const
from .words import Word, and_all, bit, cat, const, wires, zext


def fsqrt(b: CircuitBuilder, x: Word, depth_opt: bool = False) -> Word:
    """sqrt(x) as float32 words."""
    x = wires(x)
    adder = add_fast if depth_opt else add
    sx, ex, fx = fields(x)
    lead = x.shape[:-1]
    nz = nonzero_exp(b, ex)
    even = b.not_(ex[..., 0])              # even biased exponent: odd unbiased -> 2 * 1.f
    one = np.full(lead + (1,), ONE, np.int32)
    zero1 = np.zeros(lead + (1,), np.int32)
    sig = cat(fx, one)                                          # 24 bits
    m = b.mux(even[..., None], cat(zero1, sig, zero1), cat(zero1, zero1, sig))  # 26 bits
    # radicand pairs from the top: m has 26 bits = 13 pairs, then zeros
    steps = 25
    pairs = [m[..., 24 - 2 * i : 26 - 2 * i] if i < 13 else np.zeros(lead + (2,), np.int32)
             for i in range(steps)]
    r = np.zeros(lead + (1,), np.int32)
    qs: list[np.ndarray] = []
    neg = np.zeros(lead, np.int32)         # sign of the remainder
    for k in range(steps):
        w = k + 4
        rr = cat(pairs[k], zext(r, w - 2) if r.shape[-1] < w - 2 else r[..., : w - 2])
        if r.shape[-1] < w - 2:  # sign-extend the old remainder
            rr = cat(pairs[k], r, np.repeat(r[..., -1:], w - 2 - r.shape[-1], axis=-1))
        qbits = np.stack(qs[::-1], axis=-1) if qs else np.zeros(lead + (0,), np.int32)
        # operand: bit0 = neg, bit1 = 1, bits 2.. = Q ^ !neg, cin = !neg
        pos = b.not_(neg)
        opq = b.xor(zext(qbits, w - 2), pos[..., None]) if k else \
            np.broadcast_to(pos[..., None], lead + (w - 2,))
        op = cat(bit(neg), np.full(lead + (1,), ONE, np.int32), opq)
        r = adder(b, rr, op, pos)
        neg = r[..., -1]
        qs.append(b.not_(neg))
    q = np.stack(qs[::-1], axis=-1)        # 25 bits: 1.q1..q24, LSB first
    sig_r, guard = q[..., 1:], q[..., 0]
    e1 = shr_const(add(b, zext(ex, 9), const(125, 9)), 1)
    e1 = zext(e1, 10)
    inf = b.and_(and_all(b, ex), b.not_(sx))
    nan = b.and_(sx, nz)
    return round_pack(b, sx, e1, sig_r, guard, None, zero=b.not_(nz), inf=inf, nan=nan)


__all__ = ["ZERO", "fsqrt"]
