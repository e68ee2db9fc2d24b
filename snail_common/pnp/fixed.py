"""Fixed-point arithmetic for the per-point normal equations, on either backend.

The Jacobian, J^T W J and J^T W r only steer the step: an error there slows convergence
or moves the fixed point J^T W r = 0 by a small fraction of the pose's own uncertainty
(normal.py), so they need about 13 significant bits, not float32. Integer products of
that width cost about a third of a narrow float product, and integer sums over points
cost one AND per bit against ~350 for a narrow float add. Values are sign-magnitude
(``SM``: a sign wire and an unsigned magnitude word) through the products, whose signs
are then free XORs, and two's complement (``TC``) through the sums.

Floats enter with an exponent that is public (``from_float`` at a fixed scale,
saturating above it) or shared by a block of values (``block_emax``: the largest exponent
of the block, one secret per block, returned to the client with the sums), the block
floating point that keeps inverse depths and residuals of any magnitude at full
precision relative to the block's largest.

Every operation is exact integer arithmetic on truncated magnitudes, so the numpy
mirror (``FixMirror``) is bit-identical to the circuit (``FixCircuit``) by construction.
That includes the truncated products (``mul_cut``): the radix-4 partial products below a
cut are never built, about a third of a product whose low half is dropped anyway, and
the mirror sums exactly the partial products that are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from snail_common.arith import mirror as m

from .fops import F, MirrorBackend

# from_float's magnitudes count units of 2^(emax - width - SCALE_BIAS): the biased exponent
# emax (bias 127) is that of the block's top binade [2^(emax-127), 2^(emax-126))
SCALE_BIAS = 126


@dataclass(frozen=True)
class SM:
    """A sign-magnitude array: ``s`` the signs, ``m`` the magnitudes, ``w`` their width
    in bits (mirror: int64 arrays; circuit: wires, magnitudes with a trailing bit axis)."""

    s: np.ndarray
    m: np.ndarray
    w: int

    def __getitem__(self, idx) -> SM:
        return SM(self.s[idx], self.m[idx], self.w)


@dataclass(frozen=True)
class TC:
    """A two's complement array of ``w`` bits (mirror: int64; circuit: wires)."""

    v: np.ndarray
    w: int


class FixMirror:
    """numpy int64: the specification of every circuit below."""

    def __init__(self, be: MirrorBackend) -> None:
        self.be = be

    def exponent_offset(self, x, y, k: int):
        """x - y + k for exponents x, y (y may be None): what scale2 adds."""
        return np.int64(x) - (0 if y is None else np.int64(y)) + k

    def block_emax(self, x: F) -> np.ndarray:
        """The largest biased exponent over all of ``x`` (a 0-d int64)."""
        return np.int64(_exponent(x.v).max())

    def recip_block(self, z: F, width: int) -> tuple[SM, np.ndarray]:
        """1/z as block floating point without a float division: ``width``-bit magnitudes
        floor(2^(width + 23) / S) >> (e - emin) (S the 24-bit significand, e the exponent,
        emin the block's smallest), saturating at 2^width - 1 (S a power of two and e =
        emin, or z zero or subnormal), and the block exponent 253 - emin (modulo 256) at
        which from_float would have scaled them: the floor of the exact 1/z."""
        bits = np.asarray(z.v, np.float32).view(np.uint32).astype(np.int64)
        e = (bits >> 23) & 0xFF
        emin = e.min()
        top = (1 << width) - 1
        quot = (1 << (width + 23)) // ((bits & 0x7FFFFF) | (1 << 23))   # < 2^(width + 1)
        mag = np.minimum(quot >> np.minimum(e - emin, width + 1), top)
        return SM(bits >> 31, np.where(e == 0, top, mag), width), np.int64((253 - emin) % 256)

    def from_float(self, x: F, emax, width: int) -> SM:
        """x as ``width``-bit magnitudes at scale 2^(emax - width - SCALE_BIAS); above that
        scale (e > emax) the magnitude saturates. Wider than 24 bits, the significand's
        low end is zero-padded; ``emax`` may be up to 9 bits (``exponent_plus``)."""
        bits = np.asarray(x.v, np.float32).view(np.uint32).astype(np.int64)
        e = (bits >> 23) & 0xFF
        sig = np.where(e != 0, (bits & 0x7FFFFF) | (1 << 23), bits & 0x7FFFFF)
        top = sig >> (24 - width) if width <= 24 else sig << (width - 24)
        d = np.int64(emax) - e
        mag = np.where(d >= width, 0, top >> np.clip(d, 0, width - 1))
        mag = np.where(d < 0, (1 << width) - 1, mag)
        return SM(bits >> 31, mag.astype(np.int64), width)

    def unsigned(self, x, width: int) -> SM:
        """Non-negative integers (an input) as magnitudes."""
        mags = np.asarray(x, np.int64)
        return SM(np.zeros_like(mags), mags, width)

    def sign_magnitude(self, x, width: int) -> SM:
        """Integers (an input) of ``width`` magnitude bits with the sign in bit ``width``."""
        words = np.asarray(x, np.int64)
        return SM((words >> width) & 1, words & ((1 << width) - 1), width)

    def zeros_tc(self, lead: tuple[int, ...], width: int) -> TC:
        return TC(np.zeros(lead, np.int64), width)

    def index_tc(self, x: TC, idx) -> TC:
        return TC(x.v[idx], x.w)

    def stack_tc(self, xs: list[TC], axis: int) -> TC:
        return TC(np.stack([x.v for x in xs], axis), max(x.w for x in xs))

    def insert_zero(self, x: TC, pos: int) -> TC:
        """A constant 0 inserted at ``pos`` of a 1-d array."""
        return TC(np.insert(x.v, pos, 0), x.w)

    def neg(self, x: SM) -> SM:
        return SM(x.s ^ 1, x.m, x.w)

    def neg_tc(self, x: TC) -> TC:
        """-x, the same width (x is never the most negative word)."""
        return TC(-np.asarray(x.v, np.int64), x.w)

    def mul(self, x: SM, y: SM, drop: int, width: int) -> SM:
        """Signs XORed; magnitudes (|x| |y|) >> drop, kept to ``width`` bits."""
        return SM(x.s ^ y.s, ((x.m * y.m) >> drop) & ((1 << width) - 1), width)

    def mul_cut(self, x: SM, y: SM, drop: int, cut: int, width: int) -> TC:
        """The signed product x y / 2^drop from the radix-4 partial products of 2|x||y|
        (multiply.mul_radix4: digits of 2|y| + 1, minus |x|) floored at 2^cut: each of the
        T terms is floored there (a term's carry-in below 2^cut is dropped, so a negative
        one may lose up to 2 units), the sum floored at 2^(drop + 1). The magnitude is
        floor(|x y| / 2^drop) - e, 0 <= e <= 2T / 2^(drop + 1 - cut), possibly -1; TC of
        ``width`` + 1 bits, ``width`` holding the magnitude; 1 <= cut <= drop + 1."""
        xm, ym = np.broadcast_arrays(np.asarray(x.m, np.int64), np.asarray(y.m, np.int64))
        digits = 2 * ym + 1
        k = y.w + 1
        total = ((-xm - 1) >> cut) + (xm << k >> cut if k % 2 == 0 else 0)
        for j in range(0, k, 2):
            lo, hi = (digits >> (j + 1)) & 1, (digits >> (j + 2)) & 1
            if j + 1 >= k:
                total = total + (xm << j >> cut)
                continue
            row = np.where(lo == hi, 3 * xm, xm)
            term = np.where(hi == 0, -row - 1, row)
            total = total + (term << j >> cut) + (np.where(hi == 0, 1, 0) << j >> cut
                                                 if j >= cut else 0)
        mag = total >> (drop + 1 - cut)
        return TC(np.where((x.s ^ y.s) == 1, -mag, mag), width + 1)

    def mul_cut_sm(self, x: SM, y: SM, drop: int, cut: int, width: int) -> SM:
        """mul_cut's magnitude, floored at 0, with the signs XORed apart: a truncated
        product that feeds another product."""
        mag = self.mul_cut(_unsigned(x), _unsigned(y), drop, cut, width).v
        return SM(x.s ^ y.s, np.maximum(mag, 0), width)

    def constant_tc(self, value: int, width: int) -> TC:
        return TC(np.int64(value), width)

    def exponent_neg(self, y, k: int):
        """k - y for an exponent y: what scale2 adds."""
        return np.int64(k) - np.int64(y)

    def exponent_add(self, x, y, times: int = 1):
        """x + times y for exponents (y a shift amount: normalize_columns; x None: 0)."""
        return (0 if x is None else np.int64(x)) + times * np.asarray(y, np.int64)

    def normalize_columns(self, x: SM) -> tuple[SM, np.ndarray]:
        """Each column (last axis) of magnitudes shifted left by its leading zeros over
        all its entries (``x.w`` for a zero column), so its largest fills the word: the
        column's block exponent. Returns the shifted magnitudes and the shifts (columns,)."""
        m = np.asarray(x.m, np.int64)
        top = np.bitwise_or.reduce(m.reshape(-1, m.shape[-1]), axis=0)
        lz = np.array([x.w - int(v).bit_length() for v in top], np.int64)
        return SM(x.s, (m << lz) & ((1 << x.w) - 1), x.w), lz

    def nonzero(self, x) -> TC:
        """1 where the integer word (an input) is not zero, as 2-bit TC."""
        return TC((np.asarray(x, np.int64) != 0).astype(np.int64), 2)

    def sm_from_tc(self, x: TC, k: int, width: int) -> SM:
        """floor(x / 2^k) as sign and ``width``-bit magnitude (the caller bounds it)."""
        v = np.asarray(x.v, np.int64) >> k
        return SM((v < 0).astype(np.int64), np.abs(v), width)

    def add_shl(self, x: SM, y: SM, k: int, width: int) -> SM:
        """|x| + (|y| << k), x's sign kept (for magnitudes that add: y non-negative)."""
        return SM(x.s, (x.m + (y.m << k)) & ((1 << width) - 1), width)

    def shr_tc(self, x: TC, k: int) -> TC:
        """floor(x / 2^k), k bits narrower."""
        return TC(np.asarray(x.v, np.int64) >> k, x.w - k)

    def shr(self, x: SM, k: int) -> SM:
        """|x| >> k, k bits narrower: a truncation that costs no gates."""
        return SM(x.s, x.m >> k, x.w - k)

    def add_const(self, x: SM, k: int, width: int) -> SM:
        """|x| + k for a non-negative x (its sign is kept)."""
        return SM(x.s, (x.m + k) & ((1 << width) - 1), width)

    def twos(self, x: SM) -> TC:
        return TC(np.where(x.s == 1, -x.m, x.m), x.w + 1)

    def add_tc(self, x: TC, y: TC) -> TC:
        """x + y, broadcast, one bit wider than the wider (no overflow)."""
        return TC(x.v + y.v, max(x.w, y.w) + 1)

    def stack(self, xs: list[SM], axis: int) -> SM:
        return SM(np.stack([x.s for x in xs], axis), np.stack([x.m for x in xs], axis),
                  max(x.w for x in xs))

    def concat_tc(self, xs: list[TC], axis: int) -> TC:
        return TC(np.concatenate([x.v for x in xs], axis), max(x.w for x in xs))

    def to_float(self, x: TC) -> tuple[F, int]:
        """(x / 2^drop as float32, rounded to nearest even, drop): words wider than 32
        bits lose their low ``drop`` bits first (a floor)."""
        drop = max(x.w - 32, 0)
        return F(self.be, m.i2f(np.asarray(x.v, np.int64) >> drop)), drop

    def scale2(self, x: F, k) -> F:
        """x * 2^k by adding k to the exponent field modulo 256 (zeros stay zero; the
        caller keeps results in range)."""
        bits = np.asarray(x.v, np.float32).view(np.uint32).astype(np.int64)
        e = (bits >> 23) & 0xFF
        e2 = np.where(e != 0, (e + np.asarray(k, np.int64)) & 0xFF, 0)
        out = (bits & ~(0xFF << 23)) | (e2 << 23)
        return F(x.be, out.astype(np.uint32).view(np.float32))

    def exponent_plus(self, x, k: int):
        """x + k for an exponent x and k >= 0, without wrapping (9 bits in the circuit)."""
        return np.int64(x) + k

    def to_float_scaled(self, x: TC, emax, width: int) -> F:
        """from_float's inverse: the float32 nearest x * 2^(emax - width - SCALE_BIAS),
        rounded to nearest even, flushed to zero below 2^-126."""
        v = np.asarray(x.v, np.int64).astype(np.float64)
        with np.errstate(over="ignore"):
            out = (v * np.exp2(float(emax) - width - SCALE_BIAS)).astype(np.float32)
        return F(self.be, m.ftz(out))

    def sum_tc(self, x: TC) -> TC:
        """Sum over axis 0 (exact: any order gives the same integer)."""
        levels = max(int(x.v.shape[0] - 1).bit_length(), 0)
        return TC(x.v.sum(axis=0), x.w + levels)


def _unsigned(x: SM) -> SM:
    return SM(np.zeros_like(np.asarray(x.s)), x.m, x.w)


def _exponent(v) -> np.ndarray:
    return (np.asarray(v, np.float32).view(np.uint32).astype(np.int64) >> 23) & 0xFF


def fix_backend(x: F):
    """The fixed-point twin of the float backend ``x`` runs on (FixCircuit, the gates,
    lives in fixed_circuit.py, which builds on SM and TC here)."""
    if isinstance(x.be, MirrorBackend):
        return FixMirror(x.be)
    from .fixed_circuit import FixCircuit

    return FixCircuit(x.be)
