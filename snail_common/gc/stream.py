"""The garbled-table stream from garbler to evaluator (format version 1).

One header, then the garbled tables, in schedule order, cut into frames of at most
``FRAME_BYTES`` that always hold whole blocks (small steps share a frame).

Header (``HEADER.size`` bytes, little-endian): magic ``b"SNGC"``, format version, scheme,
two reserved bytes, AND gate count, input count, output count, the block size in gates, and
the 16-byte public AES key of the hash (fresh per run).

Scheme 1 (half-gates): every AND step is cut into blocks of ``block_gates`` gates (the last
one shorter); a block of m gates holds the m generator-half ciphertexts TG followed by the
m evaluator-half ciphertexts TE, 16 bytes each. The scheme byte leaves room for three-halves
garbling, whose blocks would hold a different number of ciphertexts per gate.
"""

from __future__ import annotations

import struct
from typing import NamedTuple

MAGIC = b"SNGC"
VERSION = 1
SCHEME_HALF_GATES = 1
BYTES_PER_AND = {SCHEME_HALF_GATES: 32}
FRAME_BYTES = 1 << 20
BLOCK_GATES = 8192
MAX_BLOCK_GATES = 1 << 20  # bounds what a stream header can make the evaluator allocate
KEY_BYTES = 16

HEADER = struct.Struct("<4sBBHQQQI16s")


class StreamError(Exception):
    """The stream does not match the evaluator's schedule or is malformed."""


class Header(NamedTuple):
    n_and: int
    n_inputs: int
    n_outputs: int
    block_gates: int
    key: bytes
    scheme: int = SCHEME_HALF_GATES
    version: int = VERSION

    def pack(self) -> bytes:
        return HEADER.pack(MAGIC, self.version, self.scheme, 0, self.n_and, self.n_inputs,
                           self.n_outputs, self.block_gates, self.key)

    @staticmethod
    def unpack(data: bytes) -> Header:
        magic, version, scheme, _, n_and, n_in, n_out, block, key = HEADER.unpack(data)
        if magic != MAGIC:
            raise StreamError(f"not a garbled-table stream (magic {magic!r})")
        if version != VERSION:
            raise StreamError(f"stream format version {version} is not supported "
                              f"(this build reads {VERSION})")
        if scheme not in BYTES_PER_AND:
            raise StreamError(f"unknown garbling scheme {scheme}")
        if not 1 <= block <= MAX_BLOCK_GATES:
            raise StreamError(f"block size {block} is not in 1..{MAX_BLOCK_GATES}")
        return Header(n_and, n_in, n_out, block, key, scheme, version)

    def check(self, n_and: int, n_inputs: int, n_outputs: int) -> None:
        """Raise StreamError unless the stream was garbled from a schedule of this shape."""
        if (self.n_and, self.n_inputs, self.n_outputs) != (n_and, n_inputs, n_outputs):
            raise StreamError(
                f"stream is for a circuit with {self.n_and} AND, {self.n_inputs} inputs, "
                f"{self.n_outputs} outputs; this schedule has {n_and}, {n_inputs}, {n_outputs}")
