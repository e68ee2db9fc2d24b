"""Integer products: schoolbook, Karatsuba, odd-digit radix-4 recoding, public constants.

Costs for an n x m unsigned product (AND gates):
- ``mul_schoolbook``: n*m partial products + (m-1) ripple adds of n bits, about 2nm.
- ``mul_karatsuba``: three half-size products (subtractive variant: |x0-x1| * |y1-y0|,
  so the middle product does not grow a bit) plus ~6 adders; wins over schoolbook only
  from ~32 bits on in this cost model.
- ``mul_radix4``: y is recoded into (m+1)/2 digits from {±1, ±3} read straight off its
  bits (no gates), so each row is a mux between x and a precomputed 3x (1 AND per bit)
  plus one signed add: about n*m total, the cheapest here for float significands.
``mul`` picks by width. ``mul_const`` multiplies by a public integer with one adder per
nonzero digit of its canonical signed-digit form.
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit import ONE, ZERO, CircuitBuilder

from .integer import add, add_wide, cond_negate, sub_borrow
from .shift import shl_const
from .words import Word, broadcast_lead, cat, sext, wires, zext


def mul_schoolbook(b: CircuitBuilder, x: Word, y: Word) -> Word:
    """Exact unsigned product (n+m bits) by row accumulation."""
    x, y = broadcast_lead(x, y)
    n, m = x.shape[-1], y.shape[-1]
    acc = b.and_(x, y[..., 0:1])
    out = [acc[..., 0]]
    acc = acc[..., 1:]
    for i in range(1, m):
        row = b.and_(x, y[..., i : i + 1])
        s = add_wide(b, row, acc)
        out.append(s[..., 0])
        acc = s[..., 1:]
    return np.concatenate([np.stack(out, axis=-1), acc], axis=-1)[..., : n + m]


def _abs_diff(b: CircuitBuilder, u: Word, v: Word) -> tuple[Word, np.ndarray]:
    d, borrow = sub_borrow(b, u, v)
    return cond_negate(b, d, borrow), borrow


def mul_karatsuba(b: CircuitBuilder, x: Word, y: Word, threshold: int = 32) -> Word:
    """Exact unsigned product of equal-width words, subtractive Karatsuba."""
    x, y = broadcast_lead(x, y)
    n = max(x.shape[-1], y.shape[-1])
    x, y = zext(x, n), zext(y, n)
    if n < threshold:
        return mul(b, x, y)
    h = (n + 1) // 2
    x0, x1, y0, y1 = x[..., :h], x[..., h:], y[..., :h], y[..., h:]
    z0 = mul_karatsuba(b, x0, y0, threshold)           # 2h bits
    z2 = mul_karatsuba(b, x1, y1, threshold)           # 2(n-h) bits
    dx, sx = _abs_diff(b, x0, x1)
    dy, sy = _abs_diff(b, y1, y0)
    p = mul_karatsuba(b, dx, dy, threshold)            # 2h bits
    w = 2 * h + 2
    t = add(b, zext(z0, w), zext(z2, w))
    neg = b.xor(sx, sy)
    z1 = add(b, t, b.xor(zext(p, w), neg[..., None]), neg)  # z0 + z2 -/+ p >= 0
    low = cat(z0, zext(z2, 2 * n - 2 * h))             # z0 + z2 << 2h (no overlap)
    hi = add(b, low[..., h:], zext(z1, 2 * n - h))
    return cat(low[..., :h], hi)


def mul_radix4(b: CircuitBuilder, x: Word, y: Word) -> Word:
    """Exact unsigned product (n+m bits) with odd radix-4 digits of y.

    For odd N = 2y + 1 with bits n_i: N = 2^k + sum_i (2 n_{i+1} - 1) 2^i, so the signed
    digits s_i = ±1 are wires; pairs give d = s_{2j} + 2 s_{2j+1} in {±1, ±3}: the row is
    |d| x = mux(x, 3x) with a free sign (XOR + carry in). Then x*y = (x*N - x) / 2.
    """
    x, y = broadcast_lead(x, y)
    n, m = x.shape[-1], y.shape[-1]
    lead = x.shape[:-1]
    x3 = add_wide(b, shl_const(x, 1, n + 1), x)             # 3x, n+2 bits
    xw = zext(x, n + 2)
    nb = cat(np.full(lead + (1,), ONE, np.int32), y)         # bits of N = 2y+1 (m+1 bits)
    k = m + 1                                                # N = 2^k + sum s_i 2^i, i<k
    # s_i = +1 if n_{i+1} else -1 ; digit pairs (s_{2j}, s_{2j+1})
    nbit = [nb[..., i] for i in range(k)] + [np.full(lead, ZERO, np.int32)]
    terms = []  # (shift, word, negative, carry-in)
    for j in range(0, k, 2):
        hi_plus = nbit[j + 2] if j + 1 < k else None
        lo_plus = nbit[j + 1]
        if hi_plus is None:  # last single digit s_{k-1} plus the leading 2^k: {1, 3}
            mag3 = lo_plus   # s = +1 -> 3, s = -1 -> 1
            row = b.mux(mag3[..., None], xw, x3)
            terms.append((j, zext(row, n + 3), None))
            continue
        mag3 = b.not_(b.xor(lo_plus, hi_plus))   # s_{2j} == s_{2j+1}
        neg = b.not_(hi_plus)                    # sign of s_{2j+1}
        row = b.mux(mag3[..., None], xw, x3)     # n+2 bits, unsigned
        signed = b.xor(zext(row, n + 3), neg[..., None])
        terms.append((j, signed, neg))
    if k % 2 == 0:  # leading 2^k not absorbed by a single digit
        terms.append((k, zext(xw, n + 3), None))
    # accumulate signed rows from the least significant one
    total = n + m + 2
    acc = None
    out = []
    pos = 0
    for shift, word, neg in terms:
        cin = neg if neg is not None else ZERO
        if acc is None:
            acc = add(b, sext(word, word.shape[-1]), np.zeros_like(word), cin) \
                if neg is not None else word
            pos = shift
            continue
        # emit the final low bits of acc below this row's shift
        drop = shift - pos
        out.extend(acc[..., i] for i in range(drop))
        acc = acc[..., drop:]
        pos = shift
        width = min(max(acc.shape[-1], word.shape[-1]) + 1, total - pos)
        signed_word = sext(word, width) if neg is not None else zext(word, width)
        acc = add(b, sext(acc, width), signed_word, cin)
    out.extend(acc[..., i] for i in range(acc.shape[-1]))
    full = np.stack(out, axis=-1)[..., :total]
    full = zext(full, total)
    # x*N - x = 2xy
    prod2 = add(b, full, b.not_(zext(x, total)), ONE)
    return prod2[..., 1 : n + m + 1]


def mul(b: CircuitBuilder, x: Word, y: Word, method: str = "auto") -> Word:
    """Exact unsigned product (n+m bits); ``method``: auto, schoolbook, karatsuba, radix4."""
    x, y = wires(x), wires(y)
    n, m = x.shape[-1], y.shape[-1]
    if method == "schoolbook" or (method == "auto" and min(n, m) < 8):
        return mul_schoolbook(b, x, y)
    if method == "karatsuba":
        return mul_karatsuba(b, x, y, threshold=min(n, m) // 2 + 1)
    return mul_radix4(b, x, y)


def csd_digits(c: int) -> list[tuple[int, int]]:
    """Canonical signed-digit form of c >= 0: [(position, ±1)], no two adjacent nonzero."""
    out, i = [], 0
    while c:
        if c & 1:
            d = 2 - (c & 3)  # +1 if c = 1 mod 4 else -1
            out.append((i, d))
            c -= d
        c >>= 1
        i += 1
    return out


def mul_const(b: CircuitBuilder, x: Word, c: int, bits: int | None = None) -> Word:
    """x * c for a public integer c >= 0, exact (n + c.bit_length() bits unless ``bits``).

    One adder per nonzero CSD digit after the first; each adder only spans the bits the
    new term overlaps (lower bits are final).
    """
    x = wires(x)
    n = x.shape[-1]
    total = n + max(c.bit_length(), 1) if bits is None else bits
    if c == 0:
        return np.zeros(x.shape[:-1] + (total,), np.int32)
    digits = csd_digits(c)
    if sum(1 for _, d in digits) >= c.bit_count():  # plain binary is no worse
        digits = [(i, 1) for i in range(c.bit_length()) if (c >> i) & 1]
    # accumulate from the least significant digit: bits below the next term are final
    acc_lo = []
    pos0, d0 = digits[0]
    rest = digits[1:]
    signed = False
    if d0 > 0:
        acc = x
    elif rest[0][1] > 0:  # -x + (x << k): one subtraction
        k = rest[0][0] - pos0
        acc = add(b, shl_const(x, k, n + k + 1), b.not_(zext(x, n + k + 1)), ONE)
        rest = rest[1:]
    else:  # start from -x
        acc = add(b, b.not_(zext(x, n + 1)), np.zeros(n + 1, np.int32), ONE)
        signed = True
    pos = pos0
    for p, d in rest:
        drop = p - pos
        acc_lo.extend(acc[..., i] for i in range(min(drop, acc.shape[-1])))
        if drop > acc.shape[-1]:
            fill = acc[..., -1] if signed else np.full(x.shape[:-1], ZERO, np.int32)
            acc_lo.extend([fill] * (drop - acc.shape[-1]))
            acc = np.broadcast_to(fill[..., None], x.shape[:-1] + (1,))
        else:
            acc = acc[..., drop:]
        pos = p
        width = max(acc.shape[-1], n) + 2
        a = sext(acc, width) if signed else zext(acc, width)
        term = zext(x, width)
        acc = add(b, a, term) if d > 0 else add(b, a, b.not_(term), ONE)
        signed = True
    full = np.concatenate([np.stack(acc_lo, axis=-1), acc], axis=-1) if acc_lo else acc
    full = sext(full, total) if signed else zext(full, total)
    return shl_const(full, pos0, total)
