"""float32 fields and the shared round-and-pack tail of every float op.

Layout of a float32 word (32 wires, LSB first): fraction bits 0..22, exponent 23..30,
sign 31. Flush-to-zero: an exponent field of 0 means zero whatever the fraction says.

Narrow formats: a float with ``frac`` < 23 fraction bits is stored as a float32 word whose
low 23 - frac fraction bits are the constant 0, so every narrow value is also a valid
float32 and needs no conversion back. Narrow ops read only the top ``frac`` fraction bits
of their inputs (the rest is truncated away) and round to nearest even at ``frac`` bits
with an unbounded exponent, then flush results below 2^-126 to a signed zero and send
results of 2^128 and up to a signed infinity (snail_common.arith.mirror.narrow_round).
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit import ONE, ZERO, CircuitBuilder

from .integer import add, increment
from .prefix import add_fast, increment_fast
from .words import Word, and_all, cat, const, or_all, wires, zext

FRAC = 23
BIAS = 127


def fields(x: Word, frac: int = FRAC) -> tuple[np.ndarray, Word, Word]:
    """(sign wire, 8-bit exponent word, top ``frac`` bits of the fraction)."""
    x = wires(x)
    return x[..., 31], x[..., 23:31], x[..., FRAC - frac : FRAC]


def check_frac(frac: int) -> None:
    if not 1 <= frac <= FRAC:
        raise ValueError(f"frac: fraction bits must be in 1..{FRAC}, got {frac}")


def nonzero_exp(b: CircuitBuilder, e: Word) -> np.ndarray:
    """1 for a normal (or inf/NaN) number, 0 for zero/subnormal: 7 AND gates."""
    return or_all(b, e)


def pack(sign, exp: Word, frac: Word) -> Word:
    """A float32 word; a fraction narrower than 23 bits fills the top, zeros below."""
    low = np.zeros(frac.shape[:-1] + (FRAC - frac.shape[-1],), np.int32)
    return cat(low, frac, exp, np.asarray(sign, np.int32)[..., None])


def round_pack(b: CircuitBuilder, sign, e1: Word, sig: Word, guard, sticky=None,
               zero=None, inf=None, nan=None, exact_tiny: bool = False,
               depth_opt: bool = False) -> Word:
    """Round a normalized significand to nearest-even and pack a float32 word.

    ``sig`` is frac + 1 bits with the hidden bit on top (1 unless the caller flags ``zero``);
    frac = 23 is float32, fewer bits a narrow format (module docstring).
    ``guard`` the next bit, ``sticky`` the OR of the rest (None where a tie cannot occur,
    as in division and square root). ``e1`` is a signed word (>= 10 bits) holding the
    biased exponent minus one, so the hidden bit carries it to the field value.

    float32 tininess is judged the way numpy's gradual underflow would round: a value in
    the top binade below 2^-126 becomes 2^-126 exactly when the significand is all ones
    (forcing the increment there does it); anything else below 2^-126 flushes to a
    signed zero. Narrow formats round first and flush what stays below 2^-126.
    Exponent fields >= 255 give signed infinity. Flags ``zero``/``inf``/``nan`` (wires
    or None) force those results, with nan > inf > zero precedence.
    ``exact_tiny``: the caller guarantees results below 2^-126 are exact (addition), so
    the sign of ``e1`` alone decides the flush. ``depth_opt``: log-depth increment and
    exponent update.
    """
    e1 = wires(e1)
    k = e1.shape[-1]
    frac = sig.shape[-1] - 1
    low = sig[..., 0]
    rnd = guard if sticky is None else b.and_(guard, b.or_(sticky, low))
    tiny = e1[..., -1]
    c0 = rnd if exact_tiny or frac < FRAC else b.or_(rnd, tiny)
    mant, carry = (increment_fast if depth_opt else increment)(b, sig[..., :frac], c0)
    field = (add_fast if depth_opt else add)(b, e1, const(1, k), carry)   # e1 + 1 + carry
    neg = field[..., -1]
    uf = tiny if exact_tiny else b.or_(neg, b.not_(or_all(b, field[..., : k - 1])))
    high = or_all(b, field[..., 8 : k - 1]) if k > 9 else np.zeros_like(neg)
    of = b.and_(b.not_(neg), b.or_(high, and_all(b, field[..., :8])))
    if zero is not None:
        uf = b.or_(uf, zero)
    if inf is not None:
        of = b.or_(of, inf)
    if nan is not None:
        of = b.or_(of, nan)
    uf = b.and_(uf, b.not_(of))
    kill = b.xor(uf, of)                              # exclusive now
    mant = b.and_(mant, b.not_(kill)[..., None])
    if nan is not None:
        mant = mant.copy()
        mant[..., frac - 1] = b.xor(mant[..., frac - 1], nan)
    exp = b.mux(kill[..., None], field[..., :8], of[..., None])
    return pack(sign, exp, mant)


__all__ = ["BIAS", "FRAC", "ONE", "ZERO", "check_frac", "fields", "nonzero_exp", "pack",
           "round_pack", "zext"]
