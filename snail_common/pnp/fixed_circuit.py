"""The fixed-point operations of fixed.py as gates (``FixCircuit``): each one the circuit of
its FixMirror twin, bit for bit (tests/test_loc_fixed.py holds them equal); fixed.py says
why the arithmetic is what it is."""

from __future__ import annotations

import numpy as np

from snail_common.arith import fconvert, integer, multiply, shift
from snail_common.arith.fbits import round_pack
from snail_common.arith.fdiv import nonrestoring_quotient
from snail_common.arith.prefix import add_fast
from snail_common.arith.words import broadcast_lead, cat, const, or_all, sext, zext
from snail_common.circuit import ONE, ZERO

from .fixed import SM, TC
from .fops import CircuitBackend, F


class FixCircuit:
    """The same operations as gates into ``builder``."""

    def __init__(self, be: CircuitBackend) -> None:
        self.be, self.b = be, be.b

    def block_emax(self, x: F) -> np.ndarray:
        """Max tree over the 8-bit exponent fields of all of ``x``: one compare (8 AND)
        and one 8-bit mux per element."""
        return self._extreme(np.asarray(x.v)[..., 23:31].reshape(-1, 8), largest=True)

    def _extreme(self, e: np.ndarray, largest: bool) -> np.ndarray:
        """The largest or smallest of the words ``e`` (m, bits): a tree of compares."""
        while e.shape[0] > 1:
            half = e.shape[0] // 2
            lo, hi = e[:half], e[half:2 * half]
            less = integer.lt(self.b, lo, hi)[..., None]
            pair = self.b.mux(less, lo, hi) if largest else self.b.mux(less, hi, lo)
            e = np.concatenate([pair, e[2 * half:]], axis=0)
        return e[0]

    def recip_block(self, z: F, width: int) -> tuple[SM, np.ndarray]:
        """Non-restoring division of 2^(width + 23) by the significand (fdiv.py's loop,
        ``width`` + 1 quotient bits), then from_float's shift by e - emin."""
        b = self.b
        v = np.asarray(z.v)
        e = v[..., 23:31]
        emin = self._extreme(e.reshape(-1, 8), largest=False)
        adder = add_fast if self.be.depth_opt else integer.add
        w = 25
        dvs = zext(cat(v[..., :23], np.full(v.shape[:-1] + (1,), ONE, np.int32)), w)
        q = nonrestoring_quotient(b, const(1 << 23, w), dvs, width, adder)  # width + 1 bits
        d = integer.sub(b, e, np.broadcast_to(emin, e.shape))
        stages = width.bit_length()
        gone = or_all(b, d[..., stages:])                  # d > width: all shifted out
        q = b.and_(shift.shr(b, q, d[..., :stages]), b.not_(gone)[..., None])
        mag = b.or_(q[..., :width], q[..., width:])        # 2^width saturates
        mag = b.or_(mag, b.not_(or_all(b, e))[..., None])  # zeros and subnormals
        return SM(v[..., 31], mag, width), integer.sub(b, const(253, 8), emin)

    def from_float(self, x: F, emax, width: int) -> SM:
        b = self.b
        v = np.asarray(x.v)
        e = v[..., 23:31]
        sig = np.concatenate([v[..., :23], or_all(b, e)[..., None]], axis=-1)
        pad = np.zeros(sig.shape[:-1] + (max(width - 24, 0),), np.int32)
        top = np.concatenate([pad, sig[..., max(24 - width, 0):]], axis=-1)
        em = const(int(emax), 10) if isinstance(emax, (int, np.integer)) else zext(emax, 10)
        d = integer.sub(b, em, zext(e, 10))         # 10-bit two's complement: emax - e
        stages = (width - 1).bit_length()
        over = d[..., 9]                            # e > emax: saturate
        gone = b.and_(or_all(b, d[..., stages:9]), b.not_(over))  # d >= 2^stages >= width
        mag = shift.shr(b, top, d[..., :stages])    # d in [width, 2^stages) shifts all out
        mag = b.and_(mag, b.not_(gone)[..., None])
        mag = b.or_(mag, over[..., None])
        return SM(v[..., 31], mag, width)

    def unsigned(self, x, width: int) -> SM:
        mags = zext(np.asarray(x), width)
        return SM(np.zeros(mags.shape[:-1], np.int32), mags, width)

    def sign_magnitude(self, x, width: int) -> SM:
        words = np.asarray(x)
        return SM(words[..., width], words[..., :width], width)

    def zeros_tc(self, lead: tuple[int, ...], width: int) -> TC:
        return TC(np.zeros(tuple(lead) + (width,), np.int32), width)

    def index_tc(self, x: TC, idx) -> TC:
        return TC(np.asarray(x.v)[idx], x.w)

    def stack_tc(self, xs: list[TC], axis: int) -> TC:
        w = max(x.w for x in xs)
        return TC(np.stack([sext(x.v, w) for x in xs], axis), w)

    def insert_zero(self, x: TC, pos: int) -> TC:
        v = np.asarray(x.v)
        return TC(np.concatenate([v[:pos], np.zeros((1, x.w), np.int32), v[pos:]], 0), x.w)

    def neg(self, x: SM) -> SM:
        return SM(self.b.not_(x.s), x.m, x.w)

    def neg_tc(self, x: TC) -> TC:
        return TC(integer.negate(self.b, x.v), x.w)

    def mul(self, x: SM, y: SM, drop: int, width: int) -> SM:
        xm, ym = broadcast_lead(x.m, y.m)
        prod = multiply.mul(self.b, xm, ym)
        return SM(self.b.xor(x.s, y.s), zext(prod[..., drop:], width), width)

    def mul_cut(self, x: SM, y: SM, drop: int, cut: int, width: int) -> TC:
        """Radix-4 rows built only from their bits at or above 2^cut (each row's mux and
        adder below it are never emitted); 3|x| and |x| ^ 3|x| are formed before ``x`` is
        broadcast, so a shared operand pays for them once."""
        b = self.b
        n, k = x.w, y.w + 1
        xw = zext(x.m, n + 2)
        x3 = integer.add_wide(b, shift.shl_const(x.m, 1, n + 1), x.m)
        diff = b.xor(xw, x3)
        lead = np.broadcast_shapes(np.shape(x.s), np.shape(y.s))
        ends = np.full(np.shape(y.s), ZERO, np.int32)
        digit = [b.not_(ends)] + [np.asarray(y.m)[..., i] for i in range(y.w)] + [ends, ends]
        ones = np.full(np.shape(x.s) + (1,), ONE, np.int32)
        terms = [(0, cat(b.not_(xw[..., min(cut, n):n]), ones), ZERO)]  # -|x| - 1

        def positive(at: int):
            lo = min(max(cut - at, 0), n + 2)
            return at, zext(xw[..., lo:], n + 3 - lo), ZERO

        if k % 2 == 0:
            terms.append(positive(k))
        for j in range(0, k, 2):
            lo = min(max(cut - j, 0), n + 2)
            if j + 1 >= k:
                terms.append(positive(j))
                continue
            three = b.not_(b.xor(digit[j + 1], digit[j + 2]))
            neg = b.not_(digit[j + 2])
            row = b.xor(np.broadcast_to(xw[..., lo:], lead + (n + 2 - lo,)),
                        b.and_(three[..., None], diff[..., lo:]))
            terms.append((j, cat(b.xor(row, neg[..., None]), neg[..., None]),
                          neg if j >= cut else ZERO))
        acc = _accumulate(b, terms, cut, n + y.w + 2 - cut)
        mag = sext(acc[..., drop + 1 - cut:], width + 1)
        return TC(integer.cond_negate(b, mag, b.xor(x.s, y.s)), width + 1)

    def mul_cut_sm(self, x: SM, y: SM, drop: int, cut: int, width: int) -> SM:
        """The magnitudes' product (constant signs: no negation), its sign bit clearing
        the rare -1."""
        zero = np.full(np.shape(x.s), ZERO, np.int32), np.full(np.shape(y.s), ZERO, np.int32)
        v = self.mul_cut(SM(zero[0], x.m, x.w), SM(zero[1], y.m, y.w), drop, cut, width).v
        mag = self.b.and_(v[..., :width], self.b.not_(v[..., width])[..., None])
        return SM(self.b.xor(x.s, y.s), mag, width)

    def constant_tc(self, value: int, width: int) -> TC:
        return TC(const(value, width), width)

    def exponent_neg(self, y, k: int):
        """k - y modulo 256 for an 8-bit exponent word y."""
        return integer.sub(self.b, const(k % 256, 8), y)

    def exponent_add(self, x, y, times: int = 1):
        """x + times y modulo 256 (times a power of two: a free shift of y; x None: 0)."""
        y = shift.shl_const(zext(np.asarray(y), 8), times.bit_length() - 1, 8)
        return y if x is None else integer.add(self.b, np.broadcast_to(x, y.shape), y)

    def normalize_columns(self, x: SM) -> tuple[SM, np.ndarray]:
        """An OR tree over each column's entries, its leading zeros (shift.lzc) and one
        left shift per entry (shift.shl): about 5 AND per magnitude bit."""
        b = self.b
        m = np.asarray(x.m)
        cols = m.reshape(-1, *m.shape[-2:])             # (entries, columns, bits)
        while cols.shape[0] > 1:
            half = cols.shape[0] // 2
            pair = b.or_(cols[:half], cols[half:2 * half])
            cols = np.concatenate([pair, cols[2 * half:]], axis=0)
        lz = shift.lzc(b, cols[0])                      # (columns, bits of x.w)
        stages = (x.w - 1).bit_length()                 # x.w itself: a zero column
        return SM(x.s, shift.shl(b, m, lz[..., :stages]), x.w), zext(lz, 8)

    def nonzero(self, x) -> TC:
        """OR of each word's bits, a zero sign bit above it."""
        bit = or_all(self.b, np.asarray(x))
        return TC(np.stack([bit, np.full(bit.shape, ZERO, np.int32)], -1), 2)

    def shr_tc(self, x: TC, k: int) -> TC:
        """floor(x / 2^k): the low bits leave."""
        return TC(np.asarray(x.v)[..., k:], x.w - k)

    def sm_from_tc(self, x: TC, k: int, width: int) -> SM:
        """The low bits leave (a floor), the rest is negated under its sign bit."""
        v = np.asarray(x.v)[..., k:]
        return SM(v[..., -1], integer.cond_negate(self.b, v, v[..., -1])[..., :width], width)

    def add_shl(self, x: SM, y: SM, k: int, width: int) -> SM:
        xm, ym = broadcast_lead(zext(x.m, width), shift.shl_const(y.m, k, width))
        return SM(x.s, integer.add(self.b, xm, ym), width)

    def shr(self, x: SM, k: int) -> SM:
        return SM(x.s, np.asarray(x.m)[..., k:], x.w - k)

    def add_const(self, x: SM, k: int, width: int) -> SM:
        return SM(x.s, integer.add(self.b, zext(x.m, width), const(k, width)), width)

    def twos(self, x: SM) -> TC:
        return TC(integer.cond_negate(self.b, zext(x.m, x.w + 1), x.s), x.w + 1)

    def add_tc(self, x: TC, y: TC) -> TC:
        w = max(x.w, y.w)
        xv, yv = broadcast_lead(sext(np.asarray(x.v), w), sext(np.asarray(y.v), w))
        return TC(integer.add_wide(self.b, xv, yv, signed=True), w + 1)

    def stack(self, xs: list[SM], axis: int) -> SM:
        w = max(x.w for x in xs)
        return SM(np.stack([np.asarray(x.s) for x in xs], axis),
                  np.stack([zext(x.m, w) for x in xs], axis), w)

    def concat_tc(self, xs: list[TC], axis: int) -> TC:
        w = max(x.w for x in xs)
        return TC(np.concatenate([sext(x.v, w) for x in xs], axis), w)

    def to_float(self, x: TC) -> tuple[F, int]:
        drop = max(x.w - 32, 0)
        word = sext(np.asarray(x.v)[..., drop:], 32)
        return F(self.be, fconvert.i2f(self.b, word)), drop

    def scale2(self, x: F, k) -> F:
        b = self.b
        v = np.asarray(x.v)
        e = v[..., 23:31]
        kw = const(int(k) % 256, 8) if isinstance(k, (int, np.integer)) else k
        e2 = b.and_(integer.add(b, e, kw), or_all(b, e)[..., None])
        return F(x.be, np.concatenate([v[..., :23], e2, v[..., 31:]], axis=-1))

    def exponent_plus(self, x, k: int):
        """x + k as a 9-bit word (x an 8-bit exponent word, 0 <= k < 256)."""
        return integer.add(self.b, zext(x, 9), const(k, 9))

    def to_float_scaled(self, x: TC, emax, width: int) -> F:
        """Sign and magnitude, a leading-zero normalization of the whole word, round to
        nearest even; the exponent is emax's plus the top bit's position."""
        b = self.b
        v = np.asarray(x.v)
        mag = integer.cond_negate(b, v, v[..., -1])
        top, lz = shift.normalize(b, mag)
        em = const(int(emax), 11) if isinstance(emax, (int, np.integer)) else zext(emax, 11)
        e1 = integer.sub(b, integer.add(b, em, const((x.w - 1 - width) % 2048, 11)),
                         zext(lz, 11))            # biased exponent minus one
        sticky = or_all(b, top[..., :x.w - 25])
        return F(self.be, round_pack(b, v[..., -1], e1, top[..., x.w - 24:], top[..., x.w - 25],
                                     sticky, zero=b.not_(top[..., -1])))

    def exponent_offset(self, x, y, k: int):
        """x - y + k modulo 256 for 8-bit exponent words (y may be None)."""
        total = integer.add(self.b, x, const(k % 256, 8))
        return total if y is None else integer.sub(self.b, total, y)

    def sum_tc(self, x: TC) -> TC:
        """Pairwise tree over axis 0, one bit wider per level (no overflow)."""
        v, w = np.asarray(x.v), x.w
        while v.shape[0] > 1:
            half = v.shape[0] // 2
            pair = integer.add_wide(self.b, v[:half], v[half:2 * half], signed=True)
            rest = sext(v[2 * half:], w + 1)
            v, w = np.concatenate([pair, rest], axis=0), w + 1
        return TC(v[0], w)


def _accumulate(b, terms: list, cut: int, total: int) -> np.ndarray:
    """Sum of (shift, two's complement word, carry-in) terms, each word's bit 0 at
    2^max(shift, cut), as a ``total``-bit word whose bit 0 is 2^cut (modulo 2^total):
    bits below the next term's offset are final and leave the adder."""
    terms = sorted(terms, key=lambda term: max(term[0] - cut, 0))
    lead = np.broadcast_shapes(*(np.shape(w)[:-1] for _, w, _ in terms))
    acc, pos, out = None, 0, []
    for first_bit, word, cin in terms:
        at = max(first_bit - cut, 0)
        word = np.broadcast_to(word, lead + np.shape(word)[-1:])
        if acc is None:  # -|x| - 1, which has no carry-in
            acc, pos = word, at
            continue
        out.extend(acc[..., i] for i in range(at - pos))
        acc, pos = acc[..., at - pos:], at
        w = min(max(acc.shape[-1], word.shape[-1]) + 1, total - pos)
        acc = integer.add(b, sext(acc, w), sext(word, w), np.broadcast_to(cin, lead))
    out.extend(acc[..., i] for i in range(acc.shape[-1]))
    return sext(np.stack(out, axis=-1), total)[..., :total]
