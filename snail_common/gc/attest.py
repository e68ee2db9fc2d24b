"""What a garbler signs for one run, so that its tables and zero-labels are provably its own.

The client holds a run's seed, offset and hash key, so it can garble the run again and
compare (snail_client/audit.py); a comparison proves something to others only if the
garbler committed to what it sent. For every run the garbler hashes the table stream in
stream order (every ``tables`` frame's data as sent: the header, then the tables, of
either scheme, lane or not: a lane's stream is byte for byte a single run's) with BLAKE3
(the ``blake3`` package: 6 MB in about 1 ms on one core here, SHA-256 3.4 ms), and signs
with Ed25519 (``cryptography``, OpenSSL):

- ``tables`` statement: (sid, circuit id, content hash, scheme, block size, stream digest),
  sent to the evaluator after the last frame; the evaluator checks it against the bytes
  it received before it answers, and forwards it to the client;
- ``outputs`` statement: the same fields and the BLAKE3 digest of the output zero-labels,
  sent to the client with those labels (never to the evaluator: the zero-labels and the
  active labels together are the outputs).

A statement is a domain string and its fields, each length-prefixed, so no two different
statements encode alike. Nothing here is home-made cryptography: the hash and the
signature are the libraries'; this module only fixes what is signed.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, replace

import blake3
import numpy as np
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import (
    Ed25519PrivateKey,
    Ed25519PublicKey,
)

from .labels import labels_to_bytes

DIGEST_BYTES = 32
SIGNATURE_BYTES = 64
PUBLIC_KEY_BYTES = 32
DOMAINS = {"tables": b"snail-tables/1", "outputs": b"snail-outputs/1"}
# what the garbler's certificate key signs to vouch for its signing key (net/tls.py)
ENDORSEMENT_DOMAIN = b"snail-signing-key/1"


def endorsement_message(public_key: bytes) -> bytes:
    """The bytes a garbler's TLS key signs to bind its signing key to its certificate."""
    return ENDORSEMENT_DOMAIN + public_key


class TableDigest:
    """BLAKE3 of a table stream fed frame by frame in stream order (frame boundaries do
    not matter: the digest is the concatenation's)."""

    def __init__(self) -> None:
        self._hash = blake3.blake3()
        self.size = 0

    def update(self, data: bytes | bytearray | memoryview) -> None:
        self._hash.update(data)
        self.size += len(data)

    def digest(self) -> bytes:
        return self._hash.digest()


def outputs_digest(zero_labels: np.ndarray) -> bytes:
    """BLAKE3 of the output zero-labels, in wire order (16 bytes each)."""
    return blake3.blake3(labels_to_bytes(np.asarray(zero_labels, np.uint64))).digest()


@dataclass(frozen=True)
class Statement:
    """One run's commitment: what it garbled (circuit, content hash, scheme, block size
    of the stream) for which session, and the digest of the stream; ``outputs``, the
    digest of the output zero-labels, makes it the client's ``outputs`` statement."""

    sid: bytes
    circuit: str
    content_hash: str
    scheme: int
    block_gates: int
    tables: bytes
    outputs: bytes | None = None

    @property
    def kind(self) -> str:
        return "tables" if self.outputs is None else "outputs"

    def encode(self) -> bytes:
        """The signed bytes: the domain, then each field length-prefixed."""
        fields = [self.sid, self.circuit.encode(), self.content_hash.encode(),
                  struct.pack("<BI", self.scheme, self.block_gates), self.tables]
        if self.outputs is not None:
            fields.append(self.outputs)
        return DOMAINS[self.kind] + b"".join(struct.pack("<I", len(f)) + f for f in fields)

    def with_outputs(self, zero_labels: np.ndarray) -> Statement:
        return replace(self, outputs=outputs_digest(zero_labels))

    def sign(self, key: Ed25519PrivateKey) -> bytes:
        return key.sign(self.encode())

    def verify(self, public_key: bytes, signature: bytes) -> bool:
        """Whether ``signature`` is the holder of ``public_key``'s on this statement."""
        return verify(public_key, self.encode(), signature)


def verify(public_key: bytes, message: bytes, signature: bytes) -> bool:
    """An Ed25519 signature check that answers False for a malformed key or signature."""
    if len(public_key) != PUBLIC_KEY_BYTES or len(signature) != SIGNATURE_BYTES:
        return False
    try:
        Ed25519PublicKey.from_public_bytes(public_key).verify(signature, message)
    except (InvalidSignature, ValueError):
        return False
    return True


def public_bytes(key: Ed25519PrivateKey) -> bytes:
    """The raw 32-byte public key of ``key``."""
    return key.public_key().public_bytes(serialization.Encoding.Raw,
                                         serialization.PublicFormat.Raw)
