"""The garbled-table stream from garbler to evaluator (format version 1).

One header, then the garbled tables, in schedule order, cut into frames of at most
``FRAME_BYTES`` that always hold whole blocks (small steps share a frame).

Header (``HEADER.size`` bytes, little-endian): magic ``b"SNGC"``, format version, scheme,
two reserved bytes, AND gate count, input count, output count, the block size in gates, and
the 16-byte public AES key of the hash (fresh per run).

Every AND step is cut into blocks of ``block_gates`` gates (the last one shorter); the
scheme byte says what a block of m gates holds:
- scheme 1 (half-gates): the m generator-half ciphertexts TG followed by the m
  evaluator-half ciphertexts TE, 16 bytes each (32 bytes per AND);
- scheme 2 (three-halves, threehalves.py): m G0, m G1, m G2 half-labels (8 bytes each),
  then 5 control bits per gate, plane by plane, least significant bit first, padded with
  zero bits to whole 8-byte words (24.625 bytes per AND, plus at most 7 bytes per block).
"""

from __future__ import annotations

import struct
from typing import NamedTuple

import numpy as np

MAGIC = b"SNGC"
VERSION = 1
SCHEME_HALF_GATES = 1
SCHEME_THREE_HALVES = 2
SCHEMES = {"halfgates": SCHEME_HALF_GATES, "threehalves": SCHEME_THREE_HALVES}
SCHEME_NAMES = {v: k for k, v in SCHEMES.items()}
DEFAULT_SCHEME = SCHEME_NAMES[SCHEME_HALF_GATES]  # what a peer that names none means
BYTES_PER_AND = {SCHEME_HALF_GATES: 32}  # half-gates only: three-halves has no whole number
CONTROL_BITS = 5  # three-halves control bits per AND gate
FRAME_BYTES = 1 << 20
BLOCK_GATES = 8192
MAX_BLOCK_GATES = 1 << 20  # bounds what a stream header can make the evaluator allocate
KEY_BYTES = 16

HEADER = struct.Struct("<4sBBHQQQI16s")


def scheme_id(scheme: str | int) -> int:
    """The stream's scheme number for a scheme name (or number); ValueError if unknown."""
    if isinstance(scheme, str):
        if scheme not in SCHEMES:
            raise ValueError(f"unknown garbling scheme {scheme!r} (expected one of "
                             f"{', '.join(SCHEMES)})")
        return SCHEMES[scheme]
    if scheme not in SCHEME_NAMES:
        raise ValueError(f"unknown garbling scheme {scheme}")
    return scheme


def control_words(m: int) -> int:
    """64-bit words holding the three-halves control bits of a block of m gates."""
    return (CONTROL_BITS * m + 63) // 64


def table_words(scheme: int, m: int) -> int:
    """64-bit words of the tables of a block of m gates."""
    return 4 * m if scheme == SCHEME_HALF_GATES else 3 * m + control_words(m)


def table_view(scheme: int, words: np.ndarray, m: int) -> np.ndarray:
    """A block's table words in the shape its kernel takes: (2m, 2) for half-gates, flat
    for three-halves."""
    return words.reshape(2 * m, 2) if scheme == SCHEME_HALF_GATES else words


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
        if scheme not in SCHEME_NAMES:
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
