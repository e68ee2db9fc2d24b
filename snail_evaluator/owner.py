"""The map owner's input labels at the evaluator.

A circuit of the map-owner setting takes its last ``owner_bits`` input wires from the map
owner (certificate role ``mapowner``): their labels come as ``owner_labels`` {sid} chunks
on the map owner's own link, never from the client (whose ``input_labels`` then cover the
other wires only). They may arrive before either half of their session, so they wait here,
by sid, within a byte bound: the oldest are dropped first, and a session that never comes
leaves nothing behind for long.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Any

MAX_EARLY_BYTES = 64 << 20  # owner labels held for sessions not yet started


class EarlyOwnerLabels:
    """``owner_labels`` messages of sessions whose circuit is not loaded yet."""

    def __init__(self, limit: int = MAX_EARLY_BYTES) -> None:
        self.limit = limit
        self.bytes = 0
        self._by_sid: OrderedDict[bytes, list[tuple[dict[str, Any], int]]] = OrderedDict()

    def add(self, msg: dict[str, Any], size: int) -> None:
        self._by_sid.setdefault(msg["sid"], []).append((msg, size))
        self.bytes += size
        while self.bytes > self.limit and self._by_sid:
            self.drop(next(iter(self._by_sid)))

    def take(self, sid: bytes) -> list[tuple[dict[str, Any], int]]:
        held = self._by_sid.pop(sid, [])
        self.bytes -= sum(size for _, size in held)
        return held

    def drop(self, sid: bytes) -> None:
        self.take(sid)
