"""AES-128 over whole batches of label blocks (OpenSSL through ``cryptography``).

Per step the garbler and evaluator hand AES one contiguous buffer, encrypted with one ECB
call into a preallocated output: no per-block Python work and no allocation.
"""

from __future__ import annotations

import numpy as np
from cryptography.hazmat.primitives.ciphers import Cipher, algorithms, modes

BLOCK_BYTES = 16


class AesBatch:
    """A fixed-key AES-128 permutation applied to many 16-byte blocks per call."""

    def __init__(self, key: bytes) -> None:
        if len(key) != BLOCK_BYTES:
            raise ValueError(f"AES key must be {BLOCK_BYTES} bytes, got {len(key)}")
        # ECB is what we want here: a fixed public permutation, used as a correlation-robust
        # hash; blocks never repeat because every input carries a unique tweak.
        self._update_into = Cipher(algorithms.AES(bytes(key)), modes.ECB()).encryptor().update_into

    def encrypt_into(self, src: memoryview, dst: memoryview) -> None:
        """Encrypt the bytes of ``src`` (a multiple of 16) into ``dst``, which must be one block
        longer than ``src`` (the OpenSSL update API reserves that much)."""
        self._update_into(src, dst)


def byte_view(words: np.ndarray) -> memoryview:
    """A flat byte memoryview of a C-contiguous array, for zero-copy AES calls."""
    return memoryview(words.reshape(-1).view(np.uint8))
