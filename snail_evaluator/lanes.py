"""Batching concurrent sessions of one circuit into lanes of one evaluation pass.

Sessions whose client labels arrive within ``--lane-window-ms`` of each other are
evaluated together by a LaneEvaluator (see snail_common/gc/lanes.py): each session keeps
reading its own table stream and feeds its lane; the pass advances as far as every
lane's bytes allow. A lane whose session fails is dropped (fed zero tables from then on,
its result discarded), so it never holds up the others.

Every session sees an ``EvalLane`` (``Solo`` for a session evaluated alone): ``feed``
(worker pool), ``stream_complete`` (all of this lane's bytes are in), ``wait_done`` (the
pass has finished: other lanes may still be arriving), ``output_labels``.
"""

from __future__ import annotations

import asyncio
import threading

import numpy as np

from snail_common.circuit.schedule import Schedule
from snail_common.gc import Evaluator, StreamError
from snail_common.gc.lanes import LaneEvaluator
from snail_common.gc.stream import BYTES_PER_AND, HEADER, SCHEME_HALF_GATES
from snail_common.net.batching import Batch, Batcher


class Solo:
    """A session evaluated alone."""

    lanes = 1

    def __init__(self, schedule: Schedule, labels: np.ndarray,
                 scheme: int | None = SCHEME_HALF_GATES) -> None:
        self._ev = Evaluator(schedule, labels, scheme)

    def feed(self, data: bytes) -> None:
        self._ev.feed(data)

    @property
    def stream_complete(self) -> bool:
        return self._ev.done

    async def wait_done(self) -> None:
        return

    def output_labels(self) -> np.ndarray:
        return self._ev.output_labels()

    def drop(self) -> None:
        return


class _Batch(Batch):
    def __init__(self, schedule: Schedule) -> None:
        super().__init__()
        self.schedule = schedule
        self.labels: list[np.ndarray] = []
        self.finished = asyncio.Event()
        self._loop = asyncio.get_running_loop()
        self._lock = threading.Lock()
        self._ev: LaneEvaluator | None = None
        self._fed: list[int] = []
        self._dropped: set[int] = set()
        self.failure: Exception | None = None
        self.stream_bytes = HEADER.size + BYTES_PER_AND[SCHEME_HALF_GATES] * schedule.n_and

    def join(self, labels: np.ndarray) -> int:
        self.labels.append(labels)
        self._fed.append(0)
        return len(self.labels) - 1

    def feed(self, lane: int, data: bytes) -> None:
        """Runs in the worker pool."""
        with self._lock:
            if self.failure is not None:
                raise StreamError(f"the lane batch failed: {self.failure}")
            if self._ev is None:
                self._ev = LaneEvaluator(self.schedule, self.labels)
            self._fed[lane] += len(data)
            try:
                self._ev.feed(lane, data)
            except StreamError as exc:
                self._fail(exc)
                raise
            self._check_done()

    def complete(self, lane: int) -> bool:
        return self._fed[lane] >= self.stream_bytes

    def drop(self, lane: int) -> None:
        """A failed session's lane: the others go on without its stream."""
        with self._lock:
            if self.failure is not None:
                return
            if self._ev is None:
                self._ev = LaneEvaluator(self.schedule, self.labels)
            try:
                self._ev.drop(lane)
            except StreamError as exc:
                self._fail(exc)
            self._fed[lane] = self.stream_bytes
            self._check_done()

    def _fail(self, exc: Exception) -> None:
        self.failure = exc
        self._loop.call_soon_threadsafe(self.finished.set)

    def _check_done(self) -> None:
        if self._ev is not None and self._ev.done:
            self._loop.call_soon_threadsafe(self.finished.set)

    def output_labels(self, lane: int) -> np.ndarray:
        if self.failure is not None:
            raise StreamError(f"the lane batch failed: {self.failure}")
        return self._ev.output_labels(lane)


class EvalLane:
    """One session's lane of a batch."""

    def __init__(self, batch: _Batch, lane: int) -> None:
        self._batch, self._lane = batch, lane

    @property
    def lanes(self) -> int:
        return len(self._batch.labels)

    def feed(self, data: bytes) -> None:
        self._batch.feed(self._lane, data)

    @property
    def stream_complete(self) -> bool:
        return self._batch.complete(self._lane)

    async def wait_done(self) -> None:
        await self._batch.finished.wait()

    def output_labels(self) -> np.ndarray:
        return self._batch.output_labels(self._lane)

    def drop(self) -> None:
        self._batch.drop(self._lane)


class LaneBatcher:
    """Groups sessions of one circuit by labels' arrival: see snail_common/net/batching."""

    def __init__(self, window_s: float, max_lanes: int) -> None:
        self._batcher: Batcher[_Batch] = Batcher(window_s, max_lanes)

    async def lane(self, circuit_id: str, schedule: Schedule,
                   labels: np.ndarray) -> Solo | EvalLane:
        """This session's lane of its batch, or a Solo run; ``release`` it."""
        joined = await self._batcher.join(circuit_id, circuit_id, lambda: _Batch(schedule),
                                          lambda batch: batch.join(labels), _Batch.drop)
        return Solo(schedule, labels) if joined is None else EvalLane(*joined)

    def release(self, circuit_id: str) -> None:
        self._batcher.release(circuit_id)
