"""Conversions between typed values (float32, uint64, Python ints ...) and bit arrays.

Bits are least-significant first along the last axis, matching builder word layout.
Floats are encoded by their IEEE-754 bit pattern; signed integers as two's complement.
"""

from __future__ import annotations

import numpy as np

_UINT = {8: np.uint8, 16: np.uint16, 32: np.uint32, 64: np.uint64}


def to_bits(values, bits: int, dtype: str) -> np.ndarray:
    """Values of any shape -> bool array of shape ``values.shape + (bits,)``."""
    if dtype == "int":
        arr = np.asarray(values, dtype=object)
        flat = [int(v) & ((1 << bits) - 1) for v in arr.ravel()]
        out = np.array([[(v >> i) & 1 for i in range(bits)] for v in flat], dtype=bool)
        return out.reshape(arr.shape + (bits,))
    arr = np.asarray(values, dtype=np.dtype(dtype))
    if arr.dtype == np.bool_:
        return arr[..., None].copy() if bits == 1 else _ints_to_bits(arr.astype(np.uint64), bits)
    if arr.dtype.kind == "f":
        arr = arr.view(_UINT[arr.dtype.itemsize * 8])
    return _ints_to_bits(arr.astype(np.int64).view(np.uint64) if arr.dtype.kind == "i"
                         else arr.astype(np.uint64), bits)


def _ints_to_bits(arr: np.ndarray, bits: int) -> np.ndarray:
    if bits > 64:
        raise ValueError(f"{bits}-bit words need dtype 'int'")
    shifts = np.arange(bits, dtype=np.uint64)
    return ((arr[..., None] >> shifts) & np.uint64(1)).astype(bool)


def from_bits(bits: np.ndarray, dtype: str) -> np.ndarray:
    """Inverse of to_bits: bool array (..., nbits) -> values of ``dtype``."""
    bits = np.asarray(bits, dtype=bool)
    n = bits.shape[-1]
    if dtype == "int":
        weights = [1 << i for i in range(n)]
        flat = bits.reshape(-1, n)
        vals = [sum(w for w, bit in zip(weights, row) if bit) for row in flat.tolist()]
        return np.array(vals, dtype=object).reshape(bits.shape[:-1])
    dt = np.dtype(dtype)
    if dt == np.bool_:
        return bits[..., 0].copy() if n == 1 else bits.any(axis=-1)
    if n > 64:
        raise ValueError(f"{n}-bit words need dtype 'int'")
    word = (bits.astype(np.uint64) << np.arange(n, dtype=np.uint64)).sum(axis=-1,
                                                                         dtype=np.uint64)
    if dt.kind == "f":
        return word.astype(_UINT[dt.itemsize * 8]).view(dt)
    if dt.kind == "i":
        width = dt.itemsize * 8
        if n < width:  # sign-extend narrower words
            sign = (word >> np.uint64(n - 1)) & np.uint64(1)
            word = word | (sign * (np.uint64((1 << 64) - 1) << np.uint64(n)))
        return word.view(np.int64).astype(dt)
    return word.astype(dt)


def pack_lanes(bits: np.ndarray) -> np.ndarray:
    """bool (n_wires, L) -> uint64 (n_wires, ceil(L/64)): lane j is bit j%64 of word j//64."""
    n, lanes = bits.shape
    words = max(1, -(-lanes // 64))
    padded = np.zeros((n, words * 64), dtype=bool)
    padded[:, :lanes] = bits
    return np.packbits(padded, axis=1, bitorder="little").view(np.uint64).reshape(n, words)


def unpack_lanes(words: np.ndarray, lanes: int) -> np.ndarray:
    """Inverse of pack_lanes: uint64 (n, W) -> bool (n, lanes)."""
    u8 = np.ascontiguousarray(words).view(np.uint8)
    return np.unpackbits(u8, axis=1, bitorder="little")[:, :lanes].astype(bool)
