"""Wire labels: 128-bit values as numpy uint64 pairs, and the label PRG shared by client and
garbler.

A label is one row of a ``(n, 2)`` uint64 array: word 0 holds the low 64 bits and its lowest
bit is the point-and-permute bit. The client never receives labels from the garbler: both
derive the zero-labels of the constant and input wires (slots ``0 .. n_inputs+1``) from the
client's seed with AES-CTR, so a seed and the global offset ``D`` are all the client sends.
"""

from __future__ import annotations

import secrets
import sys

import numpy as np
from cryptography.hazmat.primitives.ciphers import Cipher, algorithms, modes

if sys.byteorder != "little":  # AES blocks and the stream are the little-endian bytes of words
    raise ImportError("snail_common.gc needs a little-endian host")

LABEL_BYTES = 16
_CTR_NONCE = bytes(16)


def fresh_seed() -> bytes:
    """A new 128-bit label seed from the OS CSPRNG (one per circuit run)."""
    return secrets.token_bytes(LABEL_BYTES)


def fresh_delta() -> np.ndarray:
    """A new global offset D from the OS CSPRNG, with its point-and-permute bit set."""
    delta = labels_from_bytes(secrets.token_bytes(LABEL_BYTES))[0]
    delta[0] |= np.uint64(1)
    return delta


def check_delta(delta: np.ndarray | bytes) -> np.ndarray:
    """D as a uint64 (2,) array; raises ValueError unless its lowest bit is 1 (free-XOR with
    point-and-permute needs lsb(D) = 1 so that L0 and L0 ^ D have opposite select bits)."""
    if isinstance(delta, (bytes, bytearray, memoryview)):
        delta = labels_from_bytes(delta)[0]
    d = np.asarray(delta)
    if d.shape != (2,) or d.dtype != np.uint64:
        raise ValueError(f"delta must be a uint64 array of shape (2,), got {d.dtype} {d.shape}")
    if not int(d[0]) & 1:
        raise ValueError("delta must have its lowest bit set")
    return d


def labels_to_bytes(labels: np.ndarray) -> bytes:
    """Wire encoding of labels (16 little-endian bytes each, low word first)."""
    return np.ascontiguousarray(labels, dtype=np.uint64).tobytes()


def labels_from_bytes(data: bytes | bytearray | memoryview) -> np.ndarray:
    """Inverse of labels_to_bytes: a fresh writable (n, 2) uint64 array."""
    if len(data) % LABEL_BYTES:
        raise ValueError(f"label bytes must be a multiple of {LABEL_BYTES}, got {len(data)}")
    return np.frombuffer(data, dtype=np.uint64).reshape(-1, 2).copy()


def derive_zero_labels(seed: bytes, n: int) -> np.ndarray:
    """The first ``n`` blocks of AES-128-CTR keyed by ``seed``: zero-labels of slots 0..n-1."""
    if len(seed) != LABEL_BYTES:
        raise ValueError(f"seed must be {LABEL_BYTES} bytes, got {len(seed)}")
    if n < 0:
        raise ValueError("label count must be non-negative")
    enc = Cipher(algorithms.AES(bytes(seed)), modes.CTR(_CTR_NONCE)).encryptor()
    stream = enc.update(bytes(LABEL_BYTES * n)) + enc.finalize()
    return np.frombuffer(stream, dtype=np.uint64).reshape(n, 2).copy()


def active_input_labels(seed: bytes, delta: np.ndarray | bytes,
                        bits: np.ndarray) -> np.ndarray:
    """Labels the client sends the evaluator: slots 0 (constant 0), 1 (constant 1) and one per
    input bit, ``L0 ^ bit * D``; shape ``(len(bits) + 2, 2)``."""
    d = check_delta(delta)
    bits = np.asarray(bits)
    if bits.ndim != 1:
        raise ValueError(f"input bits must be one vector, got shape {bits.shape}")
    values = np.concatenate([[False, True], bits.astype(bool)])
    labels = derive_zero_labels(seed, values.size)
    labels[values] ^= d
    return labels
