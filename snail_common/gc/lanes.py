"""Lanes: L concurrent runs of one schedule garbled or evaluated in one pass.

A small circuit's run is a long chain of narrow steps whose fixed numpy cost dominates;
concurrent sessions of the same circuit (a fleet of clients) can share that cost as lanes
of one wider pass. Each lane keeps its own seed, offset D and AES key, and its stream is
exactly what a single-run Garbler would send for those secrets (the tests check the bytes),
so a lane garbler may serve single-run evaluators and the other way round.
"""

from __future__ import annotations

import secrets
from collections.abc import Iterator, Sequence

import numpy as np

from snail_common.circuit.ir import FIRST_INPUT
from snail_common.circuit.plan import plan_for
from snail_common.circuit.runner import first_block, next_block, run_plan
from snail_common.circuit.schedule import Schedule

from .engine import resolve
from .labels import check_delta, derive_zero_labels
from .lane_kernel import LaneHalfGates
from .native.run import NativeRun
from .stream import (
    BLOCK_GATES,
    BYTES_PER_AND,
    FRAME_BYTES,
    HEADER,
    KEY_BYTES,
    SCHEME_HALF_GATES,
    Header,
    StreamError,
)

_PER_AND = BYTES_PER_AND[SCHEME_HALF_GATES]


def _lane_rows(per_lane: Sequence[np.ndarray], n_slots: int) -> np.ndarray:
    """A (n_slots, 2L) slot array whose first rows hold each lane's given labels."""
    lanes = len(per_lane)
    labels = np.empty((n_slots, 2 * lanes), np.uint64)
    for lane, rows in enumerate(per_lane):
        labels[: len(rows), 2 * lane : 2 * lane + 2] = rows
    return labels


def _lane_views(frame: np.ndarray, words: int) -> list[memoryview]:
    """Each lane's first ``words`` table words as a byte view, uncopied on their way to
    TLS: the frame array is the views' own, never filled again."""
    return [memoryview(lane[:words]).cast("B") for lane in frame]


def _lane_labels(labels: np.ndarray, slots: np.ndarray, lane: int) -> np.ndarray:
    return labels[slots, 2 * lane : 2 * lane + 2].copy()


class LaneGarbler:
    """Garbles one run of ``schedule`` per (seed, delta, key) lane, all in one pass.

    ``frames()`` yields, per frame, a list with each lane's bytes (headers first); each
    lane's concatenated frames are that lane's stream. ``engine``: see engine.py.
    """

    def __init__(self, schedule: Schedule, seeds: Sequence[bytes],
                 deltas: Sequence[np.ndarray | bytes], keys: Sequence[bytes] | None = None,
                 block_gates: int = BLOCK_GATES, frame_bytes: int = FRAME_BYTES,
                 engine: str | None = None) -> None:
        self.engine = resolve(engine)
        if not seeds or len(seeds) != len(deltas):
            raise ValueError(f"need one delta per seed, got {len(seeds)} seeds and "
                             f"{len(deltas)} deltas")
        keys = list(keys) if keys is not None else [secrets.token_bytes(KEY_BYTES)
                                                    for _ in seeds]
        if len(keys) != len(seeds) or any(len(k) != KEY_BYTES for k in keys):
            raise ValueError(f"need one {KEY_BYTES}-byte key per lane")
        self._schedule = schedule
        self._deltas = np.array([check_delta(d) for d in deltas])
        n_in = FIRST_INPUT + schedule.n_inputs
        self._input_zero = [derive_zero_labels(seed, n_in) for seed in seeds]
        self.headers = [Header(schedule.n_and, schedule.n_inputs, len(schedule.output_slots),
                               block_gates, key) for key in keys]
        self._frame_words = max(frame_bytes, block_gates * _PER_AND) // 8
        self._outputs: list[np.ndarray] | None = None

    @property
    def lanes(self) -> int:
        return len(self.headers)

    @property
    def output_zero_labels(self) -> list[np.ndarray]:
        if self._outputs is None:
            raise RuntimeError("the streams have not been garbled to their end yet")
        return self._outputs

    def frames(self) -> Iterator[list[bytes | memoryview]]:
        s, block = self._schedule, self.headers[0].block_gates
        yield [h.pack() for h in self.headers]
        labels = _lane_rows(self._input_zero, s.n_slots)
        if self.engine == "native":
            yield from self._native_frames(labels)
            return
        kernel = LaneHalfGates([h.key for h in self.headers], block, self._deltas)
        frame = np.empty((self.lanes, self._frame_words), np.uint64)
        run = run_plan(plan_for(s), labels, kernel.garble, block)
        pos, m = 0, first_block(run)
        while m is not None:
            if pos + 4 * m > self._frame_words:
                yield _lane_views(frame, pos)
                frame, pos = np.empty_like(frame), 0
            tables = frame[:, pos : pos + 4 * m].reshape(self.lanes, 2 * m, 2)
            pos += 4 * m
            m = next_block(run, tables)
        if pos:
            yield _lane_views(frame, pos)
        self._outputs = [_lane_labels(labels, s.output_slots, k) for k in range(self.lanes)]

    def _native_frames(self, labels: np.ndarray) -> Iterator[list[memoryview]]:
        """The frames after the headers, each filled by one kernel call."""
        s = self._schedule
        run = NativeRun(s, self.headers[0].block_gates, SCHEME_HALF_GATES, labels,
                        [h.key for h in self.headers], self._deltas)
        while not run.done:
            end, used = run.fit(self._frame_words)
            if end == run.pos:
                raise RuntimeError("a block's tables exceed the frame")
            frame = np.empty((self.lanes, self._frame_words), np.uint64)
            run.run(end, frame)
            if used:
                yield _lane_views(frame, used)
        self._outputs = [_lane_labels(labels, s.output_slots, k) for k in range(self.lanes)]


class LaneEvaluator:
    """Evaluates one run of ``schedule`` per lane from each lane's active input labels;
    ``feed(lane, data)`` takes that lane's stream cut anywhere, and the pass advances as
    far as every lane's bytes allow (a lane that lags holds the others). ``engine``: see
    engine.py."""

    def __init__(self, schedule: Schedule, input_labels: Sequence[np.ndarray],
                 engine: str | None = None) -> None:
        self.engine = resolve(engine)
        self._native: NativeRun | None = None
        n_in = FIRST_INPUT + schedule.n_inputs
        for lane, rows in enumerate(input_labels):
            if np.shape(rows) != (n_in, 2):
                raise ValueError(f"lane {lane}: expected {n_in} input labels, got an array "
                                 f"of shape {np.shape(rows)}")
        self._schedule = schedule
        self._labels = _lane_rows([np.asarray(r, np.uint64) for r in input_labels],
                                  schedule.n_slots)
        self._buffers = [bytearray() for _ in input_labels]
        self._read = [0] * len(input_labels)  # bytes of each buffer already used
        self._dropped: set[int] = set()  # lanes whose streams will not come
        self.headers: list[Header | None] = [None] * len(input_labels)
        self._run = None
        self._block: int | None = None
        self._tables = np.empty((len(input_labels), 0, 2), np.uint64)

    @property
    def lanes(self) -> int:
        return len(self._buffers)

    @property
    def done(self) -> bool:
        return self._run is not None and self._block is None

    def output_labels(self, lane: int) -> np.ndarray:
        if not self.done:
            raise StreamError("the streams ended before the last garbled table")
        return _lane_labels(self._labels, self._schedule.output_slots, lane)

    def drop(self, lane: int) -> None:
        """``lane``'s stream will not come (its session failed): run it on zero tables
        from now on so the other lanes go on; its result is garbage, never to be used."""
        self._dropped.add(lane)
        self._buffers[lane].clear()
        self._read[lane] = 0
        if len(self._dropped) == self.lanes:
            return  # nobody is left to evaluate for
        if self._run is None and not self._start():
            return
        self._advance()

    def feed(self, lane: int, data: bytes | bytearray | memoryview) -> None:
        """Append bytes of ``lane``'s stream and evaluate what every lane's bytes allow."""
        if self.done and data:
            raise StreamError(f"lane {lane}: {len(data)} bytes of trailing data after the "
                              f"stream")
        if lane in self._dropped:
            return
        self._buffers[lane] += data
        if self._run is None and not self._start():
            return
        self._advance()

    def _start(self) -> bool:
        """Read every lane's header once all have arrived; start the pass."""
        live = [k for k in range(self.lanes) if k not in self._dropped]
        if any(len(self._buffers[k]) < HEADER.size for k in live):
            return False
        s = self._schedule
        for lane in live:
            header = Header.unpack(bytes(self._buffers[lane][: HEADER.size]))
            header.check(s.n_and, s.n_inputs, len(s.output_slots))
            if header.scheme != SCHEME_HALF_GATES:
                raise StreamError(f"lane {lane}: lanes run half-gates streams only")
            self.headers[lane] = header
            self._read[lane] = HEADER.size
        for lane in self._dropped:  # any key will do for a lane whose result is unused
            self.headers[lane] = self.headers[live[0]]
        blocks = {h.block_gates for h in self.headers}
        if len(blocks) != 1:
            raise StreamError(f"lanes must share one block size, got {sorted(blocks)}")
        block = blocks.pop()
        if self.engine == "native":
            self._native = NativeRun(s, block, SCHEME_HALF_GATES, self._labels,
                                     [h.key for h in self.headers])
            self._run = True  # started; _advance runs the ops
            self._block = 0
            return True
        kernel = LaneHalfGates([h.key for h in self.headers], block)
        self._tables = np.empty((self.lanes, 2 * block, 2), np.uint64)
        self._run = run_plan(plan_for(s), self._labels, kernel.evaluate, block)
        self._block = first_block(self._run)
        return True

    def _advance(self) -> None:
        if self._native is not None:
            self._advance_native()
        while self._block is not None and self._native is None:
            m = self._block
            need = _PER_AND * m
            if any(len(b) - r < need for k, (b, r) in enumerate(zip(self._buffers, self._read))
                   if k not in self._dropped):
                break
            tables = self._tables[:, : 2 * m]
            for lane, buf in enumerate(self._buffers):
                if lane in self._dropped:
                    tables[lane] = 0
                    continue
                r = self._read[lane]
                tables[lane] = np.frombuffer(buf, np.uint64, 4 * m, r).reshape(2 * m, 2)
                self._read[lane] = r + need
            self._block = next_block(self._run, tables)
        self._trim()

    def _advance_native(self) -> None:
        """_advance's native engine: one kernel call for every op each live lane's bytes
        hold the tables of."""
        run = self._native
        live = [k for k in range(self.lanes) if k not in self._dropped]
        have = min(len(self._buffers[k]) - self._read[k] for k in live) // 8
        end, words = run.fit(have)
        if end > run.pos:
            tables = np.zeros((self.lanes, max(words, 1)), np.uint64)
            for lane in live:
                r = self._read[lane]
                tables[lane, :words] = np.frombuffer(self._buffers[lane], np.uint64, words, r)
                self._read[lane] = r + 8 * words
            run.run(end, tables)
        if run.done:
            self._block = None

    def _trim(self) -> None:
        for lane, buf in enumerate(self._buffers):  # drop what was used, now and then
            if self._read[lane] > (1 << 20) or self._read[lane] == len(buf):
                del buf[: self._read[lane]]
                self._read[lane] = 0
        if self.done and any(self._buffers):
            lane = next(k for k, b in enumerate(self._buffers) if b)
            raise StreamError(f"lane {lane}: {len(self._buffers[lane])} bytes of trailing "
                              f"data after the stream")
