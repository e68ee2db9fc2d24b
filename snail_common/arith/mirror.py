"""numpy float32 reference of every float circuit, with the circuits' flush-to-zero rules.

This is the test specification: a circuit's output bits must equal these functions'
bits on finite inputs, and these equal plain numpy float32 whenever inputs and result
are normal or zero. Rules: a subnormal input is read as a zero of its sign; a result
numpy would return as a subnormal becomes a zero of its sign; overflow is a signed
infinity (as in numpy). Comparisons read subnormals as zeros too; min/max/select/neg/abs
pass their inputs through bit for bit.

Narrow formats (``frac`` < 23 fraction bits, see snail_common.arith.fbits): add, sub and
mul read the top ``frac`` fraction bits of each input, compute in float64 and round once
with ``narrow_round``. A float64 sum or product of such inputs rounded again to frac + 1
<= 24 significant bits is the correctly rounded result: 53 >= 2 (frac + 1) + 2, so the
double rounding is innocuous (Figueroa's theorem for +, -, *).
"""

from __future__ import annotations

import numpy as np

TINY = np.float32(2.0 ** -126)
FRAC = 23


def f32(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float32)


def ftz(x) -> np.ndarray:
    """Subnormals -> zeros of the same sign; everything else unchanged."""
    x = f32(x)
    with np.errstate(invalid="ignore"):
        small = np.abs(x) < TINY
    return np.where(small, np.copysign(np.float32(0), x), x).astype(np.float32)


def _op(fn, *args) -> np.ndarray:
    with np.errstate(all="ignore"):
        return ftz(fn(*(ftz(a) for a in args)))


def add(x, y, frac: int = FRAC):
    if frac < FRAC:
        return narrow_round(_wide(x, frac) + _wide(y, frac), frac)
    return _op(np.add, x, y)


def sub(x, y, frac: int = FRAC):
    if frac < FRAC:
        return narrow_round(_wide(x, frac) - _wide(y, frac), frac)
    return _op(np.subtract, x, y)


def mul(x, y, frac: int = FRAC):
    if frac < FRAC:
        return narrow_round(_wide(x, frac) * _wide(y, frac), frac)
    return _op(np.multiply, x, y)


def truncate(x, frac: int) -> np.ndarray:
    """What a narrow op reads of a float32: its top ``frac`` fraction bits, FTZ."""
    mask = np.uint32((0xFFFFFFFF << (FRAC - frac)) & 0xFFFFFFFF)
    return ftz(from_bits(bits(x) & mask))


def _wide(x, frac: int) -> np.ndarray:
    return truncate(x, frac).astype(np.float64)


def narrow_round(v, frac: int) -> np.ndarray:
    """float64 -> nearest even with ``frac`` fraction bits and an unbounded exponent, then
    below 2^-126 a signed zero and from 2^128 a signed infinity; as float32 (finite v)."""
    v = np.array(v, dtype=np.float64)  # a fresh contiguous copy, any shape
    drop = np.uint64(52 - frac)
    u = v.view(np.uint64)
    half = np.uint64((1 << (52 - frac - 1)) - 1)
    r = ((u + half + ((u >> drop) & np.uint64(1))) >> drop << drop).view(np.float64)
    with np.errstate(over="ignore"):
        out = r.astype(np.float32)
    out = np.where(np.abs(r) < 2.0 ** -126, np.copysign(np.float32(0), r), out)
    return np.where(np.abs(r) >= 2.0 ** 128, np.copysign(np.float32(np.inf), r),
                    out).astype(np.float32)


def fround(x, frac: int) -> np.ndarray:
    """float32 -> the narrow format (the circuit's fround), finite x."""
    if frac == FRAC:
        return f32(x)
    return narrow_round(ftz(x).astype(np.float64), frac)


def div(x, y):
    return _op(np.divide, x, y)


def sqrt(x):
    return _op(np.sqrt, x)


def mul_const(x, c: float):
    return mul(x, np.float32(c))


def lt(x, y):
    return ftz(x) < ftz(y)


def le(x, y):
    return ftz(x) <= ftz(y)


def eq(x, y):
    return ftz(x) == ftz(y)


def minimum(x, y):
    """y where y < x, else x (so ties, including +0/-0, return x)."""
    return np.where(lt(y, x), f32(y), f32(x))


def maximum(x, y):
    return np.where(lt(x, y), f32(y), f32(x))


def neg(x):
    return -f32(x)


def absolute(x):
    return np.abs(f32(x))


def select(c, x, y):
    """y where c else x."""
    return np.where(np.asarray(c, bool), f32(y), f32(x))


def i2f(i) -> np.ndarray:
    """int32 -> float32, round to nearest even (never subnormal)."""
    return np.asarray(i, np.int32).astype(np.float32)


def f2i(x) -> np.ndarray:
    """float32 -> int32 rounding toward zero; out of range or NaN gives INT32_MIN
    (the x86 'integer indefinite' value); subnormals give 0."""
    x = ftz(x).astype(np.float64)
    ok = np.isfinite(x) & (x > -2.0 ** 31 - 1) & (x < 2.0 ** 31)
    out = np.where(ok, np.trunc(np.where(ok, x, 0)), -2.0 ** 31)
    return out.astype(np.int64).astype(np.int32)


def bits(x) -> np.ndarray:
    """float32 -> uint32 bit patterns."""
    return f32(x).view(np.uint32)


def from_bits(u) -> np.ndarray:
    return np.asarray(u, np.uint32).view(np.float32)
