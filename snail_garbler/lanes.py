"""Batching concurrent garble requests of one circuit into lanes of one pass.

A fleet of clients sends many requests for the same small circuit; each alone is a long
chain of narrow steps whose fixed cost dominates. Requests that arrive within a short
window (``--lane-window-ms``; 0 turns batching off) are garbled together by a
LaneGarbler, each lane with its client's own seed, offset and key, and each session still
streams its own tables (byte for byte what it would get alone) on its own connection.

A session sees its lane through ``LaneView``, which quacks like a Garbler (``frames()``,
``output_zero_labels``): whichever session needs a frame first garbles the next frame of
every lane, under the batch's lock, in the worker pool; the other lanes' frames wait in
their queues. A lane whose session ends early stops collecting frames.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Hashable, Iterator

import numpy as np

from snail_common.circuit.schedule import Schedule
from snail_common.gc.lanes import LaneGarbler
from snail_common.net.batching import Batch, Batcher


class _Batch(Batch):
    def __init__(self, schedule: Schedule, block: int, frame: int) -> None:
        super().__init__()
        self.schedule, self.block, self.frame = schedule, block, frame
        self.secrets: list[tuple[bytes, bytes, bytes]] = []
        self._lock = threading.Lock()
        self._frames: Iterator[list[bytes | memoryview]] | None = None
        self._garbler: LaneGarbler | None = None
        self._queues: list[deque[bytes | memoryview] | None] = []
        self._ended = False

    def join(self, seed: bytes, delta: bytes, key: bytes) -> int:
        self.secrets.append((seed, delta, key))
        self._queues.append(deque())
        return len(self.secrets) - 1

    def next_frame(self, lane: int) -> bytes | memoryview | None:
        """Lane ``lane``'s next frame (garbling every lane's if none is queued), or None
        at the end of the stream. Runs in the worker pool."""
        with self._lock:
            queue = self._queues[lane]
            while not queue and not self._ended:
                if self._frames is None:
                    seeds, deltas, keys = zip(*self.secrets)
                    self._garbler = LaneGarbler(self.schedule, seeds, deltas, keys,
                                                self.block, self.frame)
                    self._frames = self._garbler.frames()
                parts = next(self._frames, None)
                if parts is None:
                    self._ended = True
                    break
                for q, part in zip(self._queues, parts):
                    if q is not None:
                        q.append(part)
            return queue.popleft() if queue else None

    def leave(self, lane: int) -> None:
        """The lane's session is over: stop queueing its frames."""
        with self._lock:
            self._queues[lane] = None

    def output_zero_labels(self, lane: int) -> np.ndarray:
        assert self._garbler is not None, "read after the stream"
        return self._garbler.output_zero_labels[lane]


class LaneView:
    """One session's lane of a batch, used where a Garbler would be."""

    def __init__(self, batch: _Batch, lane: int) -> None:
        self._batch, self._lane = batch, lane

    @property
    def lanes(self) -> int:
        return len(self._batch.secrets)

    def frames(self) -> Iterator[bytes | memoryview]:
        try:
            while (data := self._batch.next_frame(self._lane)) is not None:
                yield data
        finally:
            self._batch.leave(self._lane)

    @property
    def output_zero_labels(self) -> np.ndarray:
        return self._batch.output_zero_labels(self._lane)


class LaneBatcher:
    """Groups requests per (circuit, block, frame size): see snail_common/net/batching."""

    def __init__(self, window_s: float, max_lanes: int) -> None:
        self._batcher: Batcher[_Batch] = Batcher(window_s, max_lanes)

    async def lane(self, circuit_id: str, schedule: Schedule, seed: bytes, delta: bytes,
                   key: bytes, block: int, frame: int, client: Hashable = None,
                   ) -> LaneView | None:
        """This request's lane of its batch, or None to garble alone; ``release`` it.
        ``client``'s own runs under way (its requests garbled ahead) do not make it wait."""
        joined = await self._batcher.join(
            circuit_id, (circuit_id, block, frame), lambda: _Batch(schedule, block, frame),
            lambda batch: batch.join(seed, delta, key), _Batch.leave, client)
        return None if joined is None else LaneView(*joined)

    def release(self, circuit_id: str, client: Hashable = None) -> None:
        self._batcher.release(circuit_id, client)
