"""The symmetric parts of IKNP on whole batches: the PRG rows, the bit-matrix transpose and
the correlation-robust hash. 128-bit blocks are numpy uint64 pairs, as wire labels are
(``snail_common.gc.labels``), so OT outputs drop into the garbling engine unchanged.
"""

from __future__ import annotations

import numpy as np
from cryptography.hazmat.primitives.ciphers import Cipher, algorithms, modes

from ..gc.aes import BLOCK_BYTES, AesBatch, byte_view
from ..gc.halfgates import sigma

KAPPA = 128  # base OTs, and bits per block
_TRANSPOSE_BYTES = 1 << 13  # columns transposed per pass: 65,536 OTs, 8 MiB unpacked


class RowStreams:
    """One AES-128-CTR stream per base-OT key: ``take(n)`` gives the next ``n`` bytes of every
    stream as the rows of a (len(keys), n) uint8 matrix. The streams run on across batches,
    so no PRG output is ever used twice."""

    def __init__(self, keys: list[bytes]) -> None:
        self._enc = [Cipher(algorithms.AES(k), modes.CTR(bytes(BLOCK_BYTES))).encryptor()
                     for k in keys]

    def take(self, nbytes: int) -> np.ndarray:
        zeros = bytes(nbytes)
        rows = np.empty((len(self._enc), nbytes), dtype=np.uint8)
        for i, enc in enumerate(self._enc):
            rows[i] = np.frombuffer(enc.update(zeros), dtype=np.uint8)
        return rows


def transpose(rows: np.ndarray) -> np.ndarray:
    """The (KAPPA, nbytes) bit matrix as nbytes*8 blocks: bit i of block j is bit j of row i
    (little-endian bit order on both sides). Returns (nbytes*8, 2) uint64."""
    if rows.shape[0] != KAPPA:
        raise ValueError(f"transpose needs {KAPPA} rows, got {rows.shape[0]}")
    nbytes = rows.shape[1]
    out = np.empty((nbytes * 8, KAPPA // 8), dtype=np.uint8)
    for lo in range(0, nbytes, _TRANSPOSE_BYTES):
        hi = min(lo + _TRANSPOSE_BYTES, nbytes)
        bits = np.unpackbits(rows[:, lo:hi], axis=1, bitorder="little")
        out[lo * 8:hi * 8] = np.packbits(bits.T, axis=1, bitorder="little")
    return out.view(np.uint64)


class CorrelationRobustHash:
    """H(j, x) = AES_k(sigma(x) ^ j) ^ sigma(x), the tweakable correlation-robust hash of
    Guo-Katz-Wang-Yu (2020) that the half-gates engine uses too, with the OT index j as the
    tweak (in word 1) and a fixed public key k agreed per OT session."""

    def __init__(self, key: bytes) -> None:
        self._aes = AesBatch(key)

    def __call__(self, x: np.ndarray, start: int) -> np.ndarray:
        """H(start + r, x[r]) for every row r of the (m, 2) uint64 array ``x``."""
        m = len(x)
        inp = sigma(x)
        inp[:, 1] ^= np.arange(start, start + m, dtype=np.uint64)
        out = np.empty((m + 1, 2), dtype=np.uint64)  # OpenSSL's update wants a spare block
        self._aes.encrypt_into(byte_view(inp), byte_view(out))
        out = out[:m]
        out ^= sigma(x)
        return out


def pack_bits(bits: np.ndarray) -> np.ndarray:
    """A 0/1 vector as little-endian bytes, padded with zero bits to a whole byte."""
    return np.packbits(bits.astype(np.uint8), bitorder="little")


def block_of_bits(bits: np.ndarray) -> np.ndarray:
    """KAPPA bits as one (2,) uint64 block (bit i of the block = bits[i])."""
    return pack_bits(bits).view(np.uint64)
