"""Carrying the OT state machines' messages in the daemons' frames, and the map-owner
values in the bit order of the circuit.

The OT classes take and give dicts with exactly their own fields; a protocol frame may add
a session id and must fit ``messages.DATA_CHUNK``-sized pieces, so tables and id lists
travel in chunks (``chunks``) that ``BlobAssembler`` puts back together in order.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from ..net.errors import BAD_REQUEST, ProtocolError
from ..net.messages import DATA_CHUNK

OT_FIELDS = {"ot_base_a": ("a",), "ot_base_b": ("b",), "ot_ext_u": ("start", "m", "u"),
             "ot_ext_y": ("start", "y")}


def ot_part(msg: Mapping[str, Any]) -> dict[str, Any]:
    """The OT layer's view of a validated protocol message (its type and OT fields)."""
    return {"t": msg["t"], **{name: msg[name] for name in OT_FIELDS[msg["t"]]}}


def chunks(data: bytes, size: int = DATA_CHUNK) -> Iterator[tuple[int, bytes]]:
    """(offset, piece) covering ``data`` in order; one empty piece for empty data (so a
    receiver always gets a first message with the total)."""
    for offset in range(0, max(len(data), 1), size):
        yield offset, data[offset:offset + size]


class BlobAssembler:
    """The pieces of one blob of an announced length, strictly in order."""

    def __init__(self, what: str, total: int, limit: int) -> None:
        if not 0 <= total <= limit:
            raise ProtocolError(BAD_REQUEST, f"{what}: {total} bytes announced, at most "
                                             f"{limit} accepted")
        self.what, self.total = what, total
        self._parts: list[bytes] = []
        self._received = 0

    @property
    def complete(self) -> bool:
        return self._received == self.total

    def add(self, offset: int, data: bytes) -> None:
        if offset != self._received or self._received + len(data) > self.total:
            raise ProtocolError(BAD_REQUEST, f"{self.what}: a piece at offset {offset} of "
                                             f"{len(data)} bytes does not continue the "
                                             f"{self._received} of {self.total} received")
        self._parts.append(data)
        self._received += len(data)

    def data(self) -> bytes:
        return b"".join(self._parts)


def pad_bits(pads: np.ndarray) -> np.ndarray:
    """The map owner's input bits for pads of (n, 12) bytes: each float32 word's bits
    least significant first, word after word, as the circuit numbers its input wires."""
    return np.unpackbits(np.ascontiguousarray(pads, np.uint8).reshape(-1), bitorder="little")


def as_words(rows: np.ndarray) -> np.ndarray:
    """(n, 12) bytes as (n, 3) uint32 words (the circuit's world_masked/world_pad values)."""
    return np.ascontiguousarray(rows, np.uint8).view("<u4").astype(np.uint32)
