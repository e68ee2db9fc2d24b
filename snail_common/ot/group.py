"""The prime-order group of the base OTs: the Ed25519 subgroup of order l, through libsodium.

PyNaCl (1.6) exposes libsodium's Ed25519 core functions but not its Ristretto255 ones, so
the base OTs work in the prime-order subgroup of Ed25519 instead of in Ristretto255. What
Ristretto adds is that every encoding is a group element; here every point a peer sends is
checked with ``crypto_core_ed25519_is_valid_point`` (canonical encoding, on the curve, in
the order-l subgroup, not of small order) before it is used, which gives the same guarantee
for the points we accept. All curve arithmetic is libsodium's; nothing here is hand-written.
"""

from __future__ import annotations

from collections.abc import Callable

import nacl.bindings as sodium
from nacl.exceptions import CryptoError

from ..net.errors import BAD_REQUEST, ProtocolError

POINT_BYTES = sodium.crypto_core_ed25519_BYTES  # 32
SCALAR_BYTES = sodium.crypto_core_ed25519_SCALARBYTES  # 32
_WIDE = sodium.crypto_core_ed25519_NONREDUCEDSCALARBYTES  # 64: reduced mod l, bias < 2^-250

Random = Callable[[int], bytes]


def random_scalar(rng: Random) -> bytes:
    """A uniform non-zero scalar mod l from 64 random bytes."""
    while True:
        scalar = sodium.crypto_core_ed25519_scalar_reduce(rng(_WIDE))
        if any(scalar):
            return scalar


def base_mult(scalar: bytes) -> bytes:
    """scalar * G for the standard generator of the order-l subgroup."""
    return sodium.crypto_scalarmult_ed25519_base_noclamp(scalar)


def mult(scalar: bytes, point: bytes) -> bytes:
    """scalar * point (the point must have passed ``check_point``)."""
    return sodium.crypto_scalarmult_ed25519_noclamp(scalar, point)


def add(p: bytes, q: bytes) -> bytes:
    return sodium.crypto_core_ed25519_add(p, q)


def sub(p: bytes, q: bytes) -> bytes:
    return sodium.crypto_core_ed25519_sub(p, q)


def check_point(data: bytes, field: str) -> bytes:
    """``data`` if it encodes an element of the order-l subgroup other than the identity;
    else a ProtocolError naming ``field`` (a peer's bad point is bad input, not a crash)."""
    try:
        valid = len(data) == POINT_BYTES and sodium.crypto_core_ed25519_is_valid_point(data)
    except CryptoError:
        valid = False
    if not valid:
        raise ProtocolError(BAD_REQUEST, f"field {field!r}: not a point of the prime-order "
                                         "subgroup of Ed25519")
    return data
