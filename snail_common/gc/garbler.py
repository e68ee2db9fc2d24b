"""The garbler: walks the schedule over zero-labels and streams the garbled tables.

Only one frame of tables exists at a time, so memory follows the circuit's live width,
not its size; the evaluator can work on a frame while the next one is being garbled.
"""

from __future__ import annotations

import secrets
from collections.abc import Iterator

import numpy as np

from snail_common.circuit.ir import FIRST_INPUT
from snail_common.circuit.schedule import Schedule

from .halfgates import HalfGates
from .labels import check_delta, derive_zero_labels
from .plan import AndPlan, plan_for
from .slots import slot_view
from .stream import BLOCK_GATES, BYTES_PER_AND, FRAME_BYTES, SCHEME_HALF_GATES, Header


class Garbler:
    """Garbles one run of ``schedule`` for the client's ``seed`` and offset ``delta``.

    ``frames()`` yields the stream (header first); once it is exhausted,
    ``output_zero_labels`` holds what the client needs to decode.
    """

    def __init__(self, schedule: Schedule, seed: bytes, delta: np.ndarray | bytes,
                 key: bytes | None = None, block_gates: int = BLOCK_GATES,
                 frame_bytes: int = FRAME_BYTES) -> None:
        self._schedule = schedule
        self._plan = plan_for(schedule)
        self._delta = check_delta(delta).copy()
        self._input_zero = derive_zero_labels(seed, FIRST_INPUT + schedule.n_inputs)
        self.header = Header(schedule.n_and, schedule.n_inputs, len(schedule.output_slots),
                             block_gates, key if key is not None else secrets.token_bytes(16))
        self._frame_bytes = max(frame_bytes, block_gates * BYTES_PER_AND[SCHEME_HALF_GATES])
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

    def frames(self) -> Iterator[bytes]:
        """The header, then frames of whole table blocks, each at most frame_bytes long."""
        s, block = self._schedule, self.header.block_gates
        yield self.header.pack()
        labels = np.empty((s.n_slots, 2), np.uint64)
        labels[: len(self._input_zero)] = self._input_zero
        slots = slot_view(labels)
        kernel = HalfGates(self.header.key, block, self._delta)
        frame = np.empty(self._frame_bytes // 8, np.uint64)
        pos = 0
        out = np.empty((block, 2), np.uint64)
        out_slots = slot_view(out)
        step_out = np.empty((0, 2), np.uint64)  # whole-step outputs of multi-block steps
        for step in self._plan.steps:
            if not isinstance(step, AndPlan):
                step.run(labels, slots)
                continue
            n = len(step.out)
            if n > block and len(step_out) < n:
                step_out = np.empty((n, 2), np.uint64)
                step_out_slots = slot_view(step_out)
            for k in range(0, n, block):
                m = min(block, n - k)
                if pos + 4 * m > len(frame):
                    yield frame[:pos].tobytes()
                    pos = 0
                c = step_out[k : k + m] if n > block else out[:m]
                kernel.garble(labels, step.a[k : k + m], step.b[k : k + m], step.first + k,
                              frame[pos : pos + 4 * m].reshape(2 * m, 2), c)
                pos += 4 * m
            # scatter once all of the step's operands are read (its outputs may reuse them)
            slots[step.out] = step_out_slots[:n] if n > block else out_slots[:n]
        if pos:
            yield frame[:pos].tobytes()
        self._outputs = labels[s.output_slots].copy()
