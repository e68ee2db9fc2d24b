"""Label vectors cut into chunks that fit a frame, and their strict reassembly."""

from __future__ import annotations

import numpy as np

from . import messages
from .conn import Connection
from .errors import BAD_REQUEST, ProtocolError
from .messages import LABEL_BYTES, LABEL_CHUNK


def write_labels(conn: Connection, kind: str, sid: bytes, labels: np.ndarray) -> int:
    """Queue ``labels`` ((n, 2) uint64) as ``kind`` messages of at most LABEL_CHUNK labels
    each; returns the bytes written."""
    data = np.ascontiguousarray(labels, dtype=np.uint64).tobytes()
    total = len(data) // LABEL_BYTES
    sent = 0
    for start in range(0, max(total, 1), LABEL_CHUNK):
        chunk = data[start * LABEL_BYTES : (start + LABEL_CHUNK) * LABEL_BYTES]
        sent += conn.write(messages.make(kind, sid=sid, start=start, total=total,
                                         labels=chunk))
    return sent


class LabelAssembler:
    """Collects the chunks of one label vector of a known length, in order."""

    def __init__(self, kind: str, expected: int) -> None:
        self.kind = kind
        self.expected = expected
        self.received = 0
        self._labels = np.empty((expected, 2), np.uint64)

    @property
    def complete(self) -> bool:
        return self.received == self.expected

    def add(self, msg: dict) -> None:
        """Take one chunk; ProtocolError naming the field that does not fit."""
        n = len(msg["labels"]) // LABEL_BYTES
        if msg["total"] != self.expected:
            raise ProtocolError(BAD_REQUEST, f"{self.kind} field 'total' is {msg['total']}, "
                                             f"the circuit needs {self.expected} labels")
        if msg["start"] != self.received:
            raise ProtocolError(BAD_REQUEST, f"{self.kind} field 'start' is {msg['start']}, "
                                             f"expected {self.received} (chunks in order)")
        if self.received + n > self.expected or (n == 0 and self.expected):
            raise ProtocolError(BAD_REQUEST, f"{self.kind} field 'labels' holds {n} labels, "
                                             f"{self.expected - self.received} remain")
        self._labels[self.received : self.received + n] = np.frombuffer(
            msg["labels"], np.uint64).reshape(n, 2)
        self.received += n

    def labels(self) -> np.ndarray:
        if not self.complete:
            raise ProtocolError(BAD_REQUEST, f"{self.kind}: {self.received} of "
                                             f"{self.expected} labels received")
        return self._labels
