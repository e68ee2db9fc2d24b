"""The evaluator: consumes the garbled-table stream as it arrives and computes active labels.

``feed`` accepts the stream cut anywhere (frames as sent, or arbitrary socket reads); it
runs the schedule as far as the bytes received allow, so evaluation of frame k overlaps
the garbling and transfer of frame k+1.
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit.ir import FIRST_INPUT
from snail_common.circuit.schedule import Schedule

from .halfgates import HalfGates
from .plan import AndPlan, plan_for
from .slots import slot_view
from .stream import BYTES_PER_AND, HEADER, Header, StreamError


class Evaluator:
    """Evaluates one run of ``schedule`` from the client's active input labels
    (slots 0 .. n_inputs+1: constant 0, constant 1, then the inputs)."""

    def __init__(self, schedule: Schedule, input_labels: np.ndarray) -> None:
        s = self._schedule = schedule
        inputs = np.asarray(input_labels, dtype=np.uint64)
        if inputs.shape != (FIRST_INPUT + s.n_inputs, 2):
            raise ValueError(f"expected {FIRST_INPUT + s.n_inputs} input labels, "
                             f"got an array of shape {inputs.shape}")
        self._labels = np.empty((s.n_slots, 2), np.uint64)
        self._labels[: len(inputs)] = inputs
        self._slots = slot_view(self._labels)
        self._steps = plan_for(s).steps
        self._step = 0  # next step to run
        self._done_in_step = 0  # AND gates of the current step already evaluated
        self._pending = b""  # received bytes not yet usable (partial header or block)
        self.header: Header | None = None
        self._kernel: HalfGates | None = None
        self._out = self._step_out = np.empty((0, 2), np.uint64)
        self._out_slots = self._step_out_slots = slot_view(self._out)

    @property
    def done(self) -> bool:
        return self.header is not None and self._step == len(self._steps)

    def output_labels(self) -> np.ndarray:
        """Active labels of the output wires, once the whole stream has been fed."""
        if not self.done:
            raise StreamError("the stream ended before the last garbled table")
        if self._pending:
            raise StreamError(f"{len(self._pending)} bytes of trailing data after the stream")
        return self._labels[self._schedule.output_slots].copy()

    def feed(self, data: bytes | bytearray | memoryview) -> None:
        """Take the next bytes of the stream and evaluate everything they make possible."""
        if self._pending:
            data = self._pending + bytes(data)
            self._pending = b""
        if self.header is None:
            if len(data) < HEADER.size:
                self._pending = bytes(data)
                return
            self._start(Header.unpack(bytes(data[: HEADER.size])))
            data = memoryview(data)[HEADER.size :]
        used = self._run(data)
        if used < len(data):
            if self.done:
                raise StreamError(f"{len(data) - used} bytes of trailing data after the stream")
            self._pending = bytes(data[used:])

    def _start(self, header: Header) -> None:
        s = self._schedule
        header.check(s.n_and, s.n_inputs, len(s.output_slots))
        self.header = header
        self._bytes_per_and = BYTES_PER_AND[header.scheme]
        self._kernel = HalfGates(header.key, header.block_gates)
        self._out = np.empty((header.block_gates, 2), np.uint64)
        self._out_slots = slot_view(self._out)

    def _run(self, data: bytes | memoryview) -> int:
        """Run steps while the data holds the next block; returns the bytes consumed."""
        kernel, labels, slots = self._kernel, self._labels, self._slots
        block, per_and = self.header.block_gates, self._bytes_per_and
        steps, size, pos = self._steps, len(data), 0
        while self._step < len(steps):
            step = steps[self._step]
            if not isinstance(step, AndPlan):
                step.run(labels, slots)
                self._step += 1
                continue
            n, k = len(step.out), self._done_in_step
            m = min(block, n - k)
            if size - pos < per_and * m:
                break
            tables = np.frombuffer(data, np.uint64, 4 * m, pos).reshape(2 * m, 2)
            if n > block:
                if k == 0 and len(self._step_out) < n:
                    self._step_out = np.empty((n, 2), np.uint64)
                    self._step_out_slots = slot_view(self._step_out)
                c = self._step_out[k : k + m]
            else:
                c = self._out[:m]
            kernel.evaluate(labels, step.a[k : k + m], step.b[k : k + m],
                            step.first + k, tables, c)
            pos += per_and * m
            if k + m < n:
                self._done_in_step = k + m
                continue
            # the whole step is read: scatter (its outputs may reuse its operand slots)
            slots[step.out] = self._step_out_slots[:n] if n > block else self._out_slots[:m]
            self._done_in_step = 0
            self._step += 1
        return pos


def evaluate_stream(schedule: Schedule, input_labels: np.ndarray, frames) -> np.ndarray:
    """Feed every frame of an iterable stream; return the active output labels."""
    ev = Evaluator(schedule, input_labels)
    for frame in frames:
        ev.feed(frame)
    return ev.output_labels()
