"""Base OTs: a batch of random 1-out-of-2 OTs, Chou-Orlandi "simplest OT" over the
prime-order subgroup of Ed25519 (``group.py``), semi-honest.

Sender: A = aG, one A for the whole batch. Receiver, choice c_i: B_i = b_iG + c_iA.
Keys: the sender gets k_i^0 = KDF(i, A, B_i, aB_i) and k_i^1 = KDF(i, A, B_i, a(B_i - A));
the receiver gets k_i^{c_i} = KDF(i, A, B_i, b_iA). B_i is a uniform group element whatever
c_i (perfect receiver privacy); the other key needs b_i(A - ...) i.e. CDH (sender privacy
in the random-oracle model). The index i in the KDF separates the OTs sharing one A.

The keys are random (the sender does not choose them): IKNP uses them as PRG seeds, so no
chosen-message layer is needed here. Messages: sender ``ot_base_a`` {a}, receiver
``ot_base_b`` {b: the B_i concatenated}.
"""

from __future__ import annotations

import hashlib
import secrets

import numpy as np

from ..net.errors import UNEXPECTED, ProtocolError
from . import group, wire
from .group import POINT_BYTES, Random

KEY_BYTES = 16  # AES-128 keys of the IKNP PRG
_PERSON = b"snail-ot-base"


def derive_key(index: int, a: bytes, b: bytes, shared: bytes) -> bytes:
    """The KDF over the transcript points and the OT index (BLAKE2b, 128-bit output)."""
    h = hashlib.blake2b(digest_size=KEY_BYTES, person=_PERSON)
    h.update(index.to_bytes(4, "little") + a + b + shared)
    return h.digest()


class BaseSender:
    """The sender of ``count`` random OTs: ``first()`` then ``finish(reply)`` -> (k0, k1)."""

    def __init__(self, count: int, rng: Random = secrets.token_bytes) -> None:
        if count < 1:
            raise ValueError(f"base OT count must be positive, got {count}")
        self.count = count
        self._a = group.random_scalar(rng)
        self.a_point = group.base_mult(self._a)
        self._done = False

    def first(self) -> dict:
        return {"t": "ot_base_a", "a": self.a_point}

    def finish(self, msg: object) -> tuple[list[bytes], list[bytes]]:
        """Both keys of every OT from the receiver's ``ot_base_b``."""
        if self._done:
            raise ProtocolError(UNEXPECTED, "'ot_base_b' received twice")
        body = wire.blob(wire.fields(msg, "ot_base_b", ("b",)), "b", self.count * POINT_BYTES)
        aa = group.mult(self._a, self.a_point)
        keys0, keys1 = [], []
        for i in range(self.count):
            b = group.check_point(body[i * POINT_BYTES:(i + 1) * POINT_BYTES], f"b[{i}]")
            ab = group.mult(self._a, b)
            keys0.append(derive_key(i, self.a_point, b, ab))
            keys1.append(derive_key(i, self.a_point, b, group.sub(ab, aa)))
        self._done = True
        return keys0, keys1


class BaseReceiver:
    """The receiver of random OTs with choice bits ``choices``: ``reply(first)`` -> its
    message; then ``keys`` holds k_i^{c_i}."""

    def __init__(self, choices: np.ndarray, rng: Random = secrets.token_bytes) -> None:
        bits = np.asarray(choices)
        if bits.ndim != 1 or not len(bits) or not np.isin(bits, (0, 1)).all():
            raise ValueError("choices must be a non-empty vector of 0/1")
        self.choices = bits.astype(bool)
        self._rng = rng
        self.keys: list[bytes] | None = None

    def reply(self, msg: object) -> dict:
        if self.keys is not None:
            raise ProtocolError(UNEXPECTED, "'ot_base_a' received twice")
        a = group.check_point(wire.blob(wire.fields(msg, "ot_base_a", ("a",)), "a",
                                        POINT_BYTES), "a")
        points, keys = [], []
        for i, c in enumerate(self.choices):
            b = group.random_scalar(self._rng)
            b0 = group.base_mult(b)
            b1 = group.add(b0, a)  # both computed: the work does not depend on c
            points.append(b1 if c else b0)
            keys.append(derive_key(i, a, points[-1], group.mult(b, a)))
        self.keys = keys
        return {"t": "ot_base_b", "b": b"".join(points)}
