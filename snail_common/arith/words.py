"""Bit plumbing for word arrays: constants, concatenation, extension, OR/AND reductions.

A word is an int32 array of wire ids whose last axis is the bit axis, LSB first.
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit import ONE, ZERO, CircuitBuilder

Word = np.ndarray


def wires(x) -> np.ndarray:
    """Any wire-id array-like as int32."""
    return np.asarray(x, dtype=np.int32)


def const(value: int, bits: int) -> Word:
    """Public constant ``value`` (two's complement if negative) as ``bits`` wires."""
    return np.array([ONE if (value >> i) & 1 else ZERO for i in range(bits)], np.int32)


def zeros(lead: tuple[int, ...], bits: int) -> Word:
    """A word of constant-0 wires with leading shape ``lead``."""
    return np.zeros(tuple(lead) + (bits,), np.int32)


def cat(*parts) -> Word:
    """Concatenate words (low part first) after broadcasting their leading shapes.

    Every part must carry its bit axis: wrap single wires with ``bit``.
    """
    parts = [np.asarray(p, np.int32) for p in parts]
    lead = np.broadcast_shapes(*(p.shape[:-1] for p in parts))
    return np.concatenate([np.broadcast_to(p, lead + p.shape[-1:]) for p in parts], axis=-1)


def bit(x) -> Word:
    """A single wire (leading shape) as a 1-bit word."""
    return np.asarray(x, np.int32)[..., None]


def zext(x: Word, bits: int) -> Word:
    """Zero-extend (or truncate) to ``bits``."""
    x = wires(x)
    n = x.shape[-1]
    if bits <= n:
        return x[..., :bits]
    return np.concatenate([x, np.zeros(x.shape[:-1] + (bits - n,), np.int32)], axis=-1)


def sext(x: Word, bits: int) -> Word:
    """Sign-extend (or truncate) to ``bits`` by repeating the top wire."""
    x = wires(x)
    n = x.shape[-1]
    if bits <= n:
        return x[..., :bits]
    top = np.repeat(x[..., -1:], bits - n, axis=-1)
    return np.concatenate([x, top], axis=-1)


def broadcast_lead(*words: Word) -> list[Word]:
    """Broadcast words to a common leading shape, keeping each bit width."""
    words = [wires(w) for w in words]
    lead = np.broadcast_shapes(*(w.shape[:-1] for w in words))
    return [np.broadcast_to(w, lead + w.shape[-1:]) for w in words]


def reduce_tree(b: CircuitBuilder, x: Word, op) -> np.ndarray:
    """Balanced reduction of the bit axis with a 2-input gate function (log depth)."""
    x = wires(x)
    if x.shape[-1] == 0:
        raise ValueError("reduction of an empty word")
    while x.shape[-1] > 1:
        n = x.shape[-1]
        half = n // 2
        pair = op(x[..., :half], x[..., half : 2 * half])
        x = np.concatenate([pair, x[..., 2 * half :]], axis=-1) if n % 2 else pair
    return x[..., 0]


def or_all(b: CircuitBuilder, x: Word) -> np.ndarray:
    """1 if any bit is set: n-1 AND gates."""
    if wires(x).shape[-1] == 0:
        return np.zeros(wires(x).shape[:-1], np.int32)
    return reduce_tree(b, x, b.or_)


def and_all(b: CircuitBuilder, x: Word) -> np.ndarray:
    """1 if every bit is set: n-1 AND gates."""
    if wires(x).shape[-1] == 0:
        return np.ones(wires(x).shape[:-1], np.int32)
    return reduce_tree(b, x, b.and_)


def is_zero(b: CircuitBuilder, x: Word) -> np.ndarray:
    return b.not_(or_all(b, x))
