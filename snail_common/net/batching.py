"""When concurrent sessions of one circuit share a pass (lanes): the daemons' batching
window, the same for the garbler (requests) and the evaluator (client labels).

A session waits for a window only while another run of its circuit is under way: a
lone client, whose sessions follow each other, never waits; a fleet, whose sessions
overlap, forms batches of up to ``max_lanes``. Where the role knows whose a session is
(``who``: the garbler's client connection), that client's own runs do not count: a lone
client's garbled-ahead requests overlap each other, and each would otherwise wait out
the window before its first table. What a batch holds and does is the
role's business (``Batch`` subclasses); this module only decides who runs with whom.
"""

from __future__ import annotations

import asyncio
from collections import Counter
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar


class Batch:
    """Sessions gathered for one pass; ``ready`` resolves when the window closes."""

    def __init__(self) -> None:
        self.ready = asyncio.get_running_loop().create_future()
        self.size = 0

    def close(self) -> None:
        if not self.ready.done():
            self.ready.set_result(None)


B = TypeVar("B", bound=Batch)


class Batcher(Generic[B]):
    """Batches per group (a circuit and whatever else must match) within ``window_s``."""

    def __init__(self, window_s: float, max_lanes: int) -> None:
        self.window_s, self.max_lanes = window_s, max_lanes
        self._running: Counter[str] = Counter()  # runs under way, per circuit
        self._own: Counter[tuple[str, Hashable]] = Counter()  # of them, per (circuit, who)
        self._open: dict[Hashable, B] = {}

    async def join(self, circuit_id: str, group: Hashable, new: Callable[[], B],
                   add: Callable[[B], int], leave: Callable[[B, int], None],
                   who: Hashable | None = None) -> tuple[B, int] | None:
        """(batch, lane) once the batch's window has closed, or None to run alone: when
        batching is off, when no other run of the circuit is under way (runs of the same
        ``who`` are not other runs), or when nobody else came. ``add`` puts the session
        into a batch (returns its lane), ``leave`` takes it out if the session is
        cancelled while it waits. Every return is a run: ``release`` it (with the same
        ``who``) when it ends."""
        batch = self._open.get(group)
        others = self._running[circuit_id] - self._own[circuit_id, who]
        if self.window_s <= 0 or self.max_lanes <= 1 or (batch is None and not others):
            self._start(circuit_id, who)
            return None
        if batch is None:
            batch = self._open[group] = new()
            asyncio.get_running_loop().call_later(self.window_s, self._close, group, batch)
        lane = add(batch)
        batch.size += 1
        if batch.size >= self.max_lanes:
            self._close(group, batch)
        try:
            await asyncio.shield(batch.ready)
        except asyncio.CancelledError:
            leave(batch, lane)
            raise
        self._start(circuit_id, who)
        return None if batch.size == 1 else (batch, lane)

    def _start(self, circuit_id: str, who: Hashable | None) -> None:
        self._running[circuit_id] += 1
        if who is not None:
            self._own[circuit_id, who] += 1

    def release(self, circuit_id: str, who: Hashable | None = None) -> None:
        """A run that ``join`` let start (alone or in a batch) is over."""
        _drop(self._running, circuit_id)
        if who is not None:
            _drop(self._own, (circuit_id, who))

    def _close(self, group: Hashable, batch: B) -> None:
        if self._open.get(group) is batch:
            del self._open[group]
        batch.close()


def _drop(counter: Counter, key: Hashable) -> None:
    """One run fewer under ``key``; the key goes with its last run."""
    counter[key] -= 1
    if counter[key] <= 0:
        del counter[key]
