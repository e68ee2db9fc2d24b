"""The garbler: walks the schedule over zero-labels and streams the garbled tables.

Only one frame of tables exists at a time, so memory follows the circuit's live width,
not its size; the evaluator can work on a frame while the next one is being garbled.
"""

from __future__ import annotations

import secrets
from collections.abc import Iterator

import numpy as np

from snail_common.circuit.ir import FIRST_INPUT
from snail_common.circuit.plan import plan_for
from snail_common.circuit.runner import AndKernel, first_block, next_block, run_plan
from snail_common.circuit.schedule import Schedule

from .engine import resolve
from .halfgates import HalfGates
from .labels import check_delta, derive_zero_labels
from .native.run import NativeRun
from .stream import (
    BLOCK_GATES,
    FRAME_BYTES,
    KEY_BYTES,
    MAX_BLOCK_GATES,
    SCHEME_HALF_GATES,
    Header,
    scheme_id,
    table_view,
    table_words,
)
from .threehalves import ThreeHalves, control_key


class Garbler:
    """Garbles one run of ``schedule`` for the client's ``seed`` and offset ``delta`` with
    ``scheme`` ("halfgates" or "threehalves", or the stream's scheme number).

    ``frames()`` yields the stream (header first); once it is exhausted,
    ``output_zero_labels`` holds what the client needs to decode. ``engine`` picks the
    engine (engine.py; the stream is the same on either).
    """

    def __init__(self, schedule: Schedule, seed: bytes, delta: np.ndarray | bytes,
                 key: bytes | None = None, block_gates: int = BLOCK_GATES,
                 frame_bytes: int = FRAME_BYTES, scheme: str | int = SCHEME_HALF_GATES,
                 engine: str | None = None) -> None:
        scheme = scheme_id(scheme)
        self.engine = resolve(engine)
        if not 1 <= block_gates <= MAX_BLOCK_GATES:
            raise ValueError(f"block_gates must be in 1..{MAX_BLOCK_GATES}, got {block_gates}")
        if key is not None and len(key) != KEY_BYTES:
            raise ValueError(f"key must be {KEY_BYTES} bytes, got {len(key)}")
        self._schedule = schedule
        self._plan = plan_for(schedule)
        self._delta = check_delta(delta).copy()
        self._input_zero = derive_zero_labels(seed, FIRST_INPUT + schedule.n_inputs)
        # three-halves' per-gate random bits: secret to the garbler, reproducible from the seed
        self._random_key = control_key(seed) if scheme != SCHEME_HALF_GATES else None
        key = key if key is not None else secrets.token_bytes(KEY_BYTES)
        self.header = Header(schedule.n_and, schedule.n_inputs, len(schedule.output_slots),
                             block_gates, key, scheme)
        self._frame_bytes = max(frame_bytes, 8 * table_words(scheme, block_gates))
        self._outputs: np.ndarray | None = None

    @property
    def input_zero_labels(self) -> np.ndarray:
        """Zero-labels of slots 0 .. n_inputs+1 (constants, then inputs)."""
        return self._input_zero.copy()

    @property
    def output_zero_labels(self) -> np.ndarray:
        if self._outputs is None:
            raise RuntimeError("the stream has not been garbled to its end yet")
        return self._outputs

    def frames(self) -> Iterator[bytes | memoryview]:
        """The header, then frames of whole table blocks, each at most frame_bytes long.
        A frame is a byte view of the array the blocks were garbled into (a new array per
        frame, never written again: the frame goes to TLS without a copy)."""
        s, block = self._schedule, self.header.block_gates
        yield self.header.pack()
        labels = np.empty((s.n_slots, 2), np.uint64)
        labels[: len(self._input_zero)] = self._input_zero
        if self.engine == "native":
            yield from self._native_frames(labels)
            self._outputs = labels[s.output_slots].copy()
            return
        scheme = self.header.scheme
        frame = np.empty(self._frame_bytes // 8, np.uint64)
        run = run_plan(self._plan, labels, self._and_kernel(), block)
        pos, m = 0, first_block(run)
        while m is not None:  # each block's tables go to the frame's next free rows
            w = table_words(scheme, m)
            if pos + w > len(frame):
                yield memoryview(frame[:pos]).cast("B")
                frame, pos = np.empty_like(frame), 0
            tables = table_view(scheme, frame[pos : pos + w], m)
            pos += w
            m = next_block(run, tables)
        if pos:
            yield memoryview(frame[:pos]).cast("B")
        self._outputs = labels[s.output_slots].copy()

    def _and_kernel(self) -> AndKernel:
        """The numpy engine's AND kernel of this run's scheme (a failpoint's garbler
        wraps it: snail_garbler/cheats.py)."""
        h = self.header
        kernel = (HalfGates(h.key, h.block_gates, self._delta) if h.scheme == SCHEME_HALF_GATES
                  else ThreeHalves(h.key, h.block_gates, self._delta, self._random_key))
        return kernel.garble

    def _native_frames(self, labels: np.ndarray) -> Iterator[memoryview]:
        """The frames after the header, each filled by one kernel call."""
        h = self.header
        run = NativeRun(self._schedule, h.block_gates, h.scheme, labels, [h.key],
                        self._delta.reshape(1, 2), self._random_key)
        words = self._frame_bytes // 8
        while not run.done:
            end, used = run.fit(words)
            if end == run.pos:
                raise RuntimeError("a block's tables exceed the frame")
            frame = np.empty((1, words), np.uint64)
            run.run(end, frame)
            if used:
                yield memoryview(frame[0, :used]).cast("B")
