"""Label vectors cut into chunks that fit a frame, and their strict reassembly."""

from __future__ import annotations

import numpy as np

from . import messages
from .conn import Connection
from .errors import BAD_REQUEST, ProtocolError
from .messages import LABEL_BYTES, LABEL_CHUNK


def write_labels(conn: Connection, kind: str, sid: bytes, labels: np.ndarray,
                 first: int = 0, total: int | None = None) -> int:
    """Queue ``labels`` ((n, 2) uint64) as ``kind`` messages of at most LABEL_CHUNK labels
    each; returns the bytes written. They are entries ``first``.. of a vector of ``total``
    labels (default: all of it), so a vector may be sent in several runs."""
    data = np.ascontiguousarray(labels, dtype=np.uint64).tobytes()
    count = len(data) // LABEL_BYTES
    total = count if total is None else total
    sent = 0
    for start in range(0, max(count, 1), LABEL_CHUNK):
        chunk = data[start * LABEL_BYTES : (start + LABEL_CHUNK) * LABEL_BYTES]
        sent += conn.write(messages.make(kind, sid=sid, start=first + start, total=total,
                                         labels=chunk))
    return sent


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """The [start, stop) runs of True in a bool vector."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


class LabelAssembler:
    """Collects the chunks of one label vector of a known length. Chunks may come in any
    order (a client sends the labels of a frame's fixed inputs ahead of the others), but
    each label exactly once: a second label for a wire would hand over its other value."""

    def __init__(self, kind: str, expected: int) -> None:
        self.kind = kind
        self.expected = expected
        self.received = 0
        self._labels = np.empty((expected, 2), np.uint64)
        self._have = np.zeros(expected, bool)

    @property
    def complete(self) -> bool:
        return self.received == self.expected

    def add(self, msg: dict) -> None:
        """Take one chunk; ProtocolError naming the field that does not fit."""
        n = len(msg["labels"]) // LABEL_BYTES
        if msg["total"] != self.expected:
            raise ProtocolError(BAD_REQUEST, f"{self.kind} field 'total' is {msg['total']}, "
                                             f"the circuit needs {self.expected} labels")
        start = msg["start"]
        if not 0 <= start < max(self.expected, 1):
            raise ProtocolError(BAD_REQUEST, f"{self.kind} field 'start' is {start}, "
                                             f"outside the {self.expected} labels")
        if start + n > self.expected or (n == 0 and self.expected):
            raise ProtocolError(BAD_REQUEST, f"{self.kind} field 'labels' holds {n} labels "
                                             f"from {start}, of {self.expected}")
        if self._have[start : start + n].any():
            raise ProtocolError(BAD_REQUEST, f"{self.kind} field 'start' is {start}: labels "
                                             f"{start}..{start + n - 1} overlap ones received")
        self._labels[start : start + n] = np.frombuffer(msg["labels"], np.uint64).reshape(n, 2)
        self._have[start : start + n] = True
        self.received += n

    def labels(self) -> np.ndarray:
        if not self.complete:
            raise ProtocolError(BAD_REQUEST, f"{self.kind}: {self.received} of "
                                             f"{self.expected} labels received")
        return self._labels
