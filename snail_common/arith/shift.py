"""Shifts by public and secret amounts, leading-zero count and normalization.

A secret shift is a logarithmic barrel shifter: stage j moves the word by 2^j under
amount bit j, one mux (1 AND) per bit that can differ. Right shifts can collect the
bits that fall off into a sticky bit, which is what float rounding needs.
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit import CircuitBuilder

from .words import Word, or_all, wires


def shl_const(x: Word, k: int, bits: int | None = None) -> Word:
    """x << k (zeros in), truncated/extended to ``bits`` (default: same width). Free."""
    x = wires(x)
    n = x.shape[-1] if bits is None else bits
    out = np.zeros(x.shape[:-1] + (n,), np.int32)
    if k < n:
        src = x[..., : max(0, n - k)]
        out[..., k : k + src.shape[-1]] = src
    return out


def shr_const(x: Word, k: int, arithmetic: bool = False) -> Word:
    """x >> k (logical, or arithmetic repeating the sign wire). Free."""
    x = wires(x)
    n = x.shape[-1]
    fill = np.repeat(x[..., -1:], min(k, n), axis=-1) if arithmetic else \
        np.zeros(x.shape[:-1] + (min(k, n),), np.int32)
    return np.concatenate([x[..., min(k, n):], fill], axis=-1)


def _stage_bits(amount: Word) -> list[np.ndarray]:
    amount = wires(amount)
    return [amount[..., j] for j in range(amount.shape[-1])]


def shl(b: CircuitBuilder, x: Word, amount: Word) -> Word:
    """x << amount (secret amount word, LSB first); amounts >= n give 0."""
    x = wires(x)
    n = x.shape[-1]
    for j, sel in enumerate(_stage_bits(amount)):
        k = 1 << j
        shifted = shl_const(x, k) if k < n else np.zeros_like(x)
        x = b.mux(sel[..., None], x, shifted)
    return x


def shr(b: CircuitBuilder, x: Word, amount: Word, arithmetic: bool = False) -> Word:
    """x >> amount (logical or arithmetic) by a secret amount."""
    x = wires(x)
    n = x.shape[-1]
    for j, sel in enumerate(_stage_bits(amount)):
        k = 1 << j
        x = b.mux(sel[..., None], x, shr_const(x, min(k, n), arithmetic))
    return x


def shr_sticky(b: CircuitBuilder, x: Word, amount: Word, sticky=0,
               order: str = "small") -> tuple[Word, np.ndarray]:
    """(x >> amount, sticky | OR of every bit shifted out) by a secret amount.

    ``order`` chooses whether the 1-bit or the largest stage comes first (the AND count
    differs with where the known-zero bits sit; callers pick the cheaper).
    """
    x = wires(x)
    n = x.shape[-1]
    st = np.broadcast_to(wires(sticky), x.shape[:-1]).astype(np.int32)
    stages = list(enumerate(_stage_bits(amount)))
    if order == "large":
        stages = stages[::-1]
    for j, sel in stages:
        k = min(1 << j, n)
        st = b.or_(st, b.and_(sel, or_all(b, x[..., :k])))
        x = b.mux(sel[..., None], x, shr_const(x, k))
    return x, st


def normalize(b: CircuitBuilder, x: Word, stages: int | None = None) -> tuple[Word, Word]:
    """Shift x left until its top bit is 1: (shifted x, shift amount word).

    Leading-zero count fused with the shifter: stage 2^j tests whether the top 2^j bits
    are zero (2^j - 1 AND gates) and shifts by 2^j if so. A zero word comes out as zero
    with the amount of all stages.
    """
    x = wires(x)
    n = x.shape[-1]
    if stages is None:
        stages = max(1, (n - 1).bit_length())
    amt = []
    for j in reversed(range(stages)):
        k = 1 << j
        z = b.not_(or_all(b, x[..., n - min(k, n):]))
        amt.append(z)
        # bits n-k .. k-1 are 0 both when shifting (top k bits zero) and as shifted-in
        # zeros, so they keep their value for free
        keep = np.zeros(n, bool)
        keep[max(0, n - k) : min(k, n)] = True
        out = x.copy()
        out[..., ~keep] = b.mux(z[..., None], x[..., ~keep], shl_const(x, k)[..., ~keep])
        x = out
    return x, np.stack(amt[::-1], axis=-1)


def lzc(b: CircuitBuilder, x: Word) -> Word:
    """Number of leading zeros of x (n for x = 0), as ceil(log2(n+1)) bits.

    Divide and conquer: a block is (all-zero flag, count of its leading zeros); two
    halves merge with one AND for the flag and one mux per count bit.
    """
    x = wires(x)
    n = x.shape[-1]
    size = 1
    while size < n + 1:
        size *= 2
    # pad below the LSB with a 1 then zeros, so zero input counts n and no block is empty
    pad = np.zeros(x.shape[:-1] + (size - n,), np.int32)
    pad[..., -1] = 1
    x = np.concatenate([pad, x], axis=-1)
    zero = b.not_(x)  # blocks of one bit: flag = !bit, count = (no bits)
    count = np.zeros(x.shape + (0,), np.int32)
    while zero.shape[-1] > 1:
        lo_z, hi_z = zero[..., 0::2], zero[..., 1::2]
        lo_c, hi_c = count[..., 0::2, :], count[..., 1::2, :]
        merged = b.mux(hi_z[..., None], hi_c, lo_c)
        count = np.concatenate([merged, hi_z[..., None]], axis=-1)
        zero = b.and_(lo_z, hi_z)
    bits = (n).bit_length()
    return count[..., 0, :bits]
