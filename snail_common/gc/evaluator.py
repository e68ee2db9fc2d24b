"""The evaluator: consumes the garbled-table stream as it arrives and computes active labels.

``feed`` accepts the stream cut anywhere (frames as sent, or arbitrary socket reads); it
runs the schedule as far as the bytes received allow, so evaluation of frame k overlaps
the garbling and transfer of frame k+1. Tables are read in place from the caller's buffer;
only a block cut by a read boundary is copied (once) into a pending buffer.
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit.ir import FIRST_INPUT
from snail_common.circuit.schedule import Schedule

from .halfgates import HalfGates
from .plan import AndOutputs, AndPlan, Scratch, plan_for
from .slots import part, slot_view
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
        self._scratch = Scratch()
        self._steps = plan_for(s).steps
        self._step = 0  # next step to run
        self._done_in_step = 0  # AND gates of the current step already evaluated
        self._need = HEADER.size  # bytes the next unit of work (header or block) takes
        self._pending = bytearray()  # the start of that unit, when a read cut it
        self.header: Header | None = None
        self._kernel: HalfGates | None = None
        self._outputs: AndOutputs | None = None

    @property
    def done(self) -> bool:
        return self.header is not None and self._step == len(self._steps)

    def output_labels(self) -> np.ndarray:
        """Active labels of the output wires, once the whole stream has been fed."""
        if not self.done:
            raise StreamError("the stream ended before the last garbled table")
        return self._labels[self._schedule.output_slots].copy()

    def feed(self, data: bytes | bytearray | memoryview) -> None:
        """Take the next bytes of the stream and evaluate everything they make possible."""
        view = memoryview(data).cast("B")
        if self._pending:
            take = min(len(view), self._need - len(self._pending))
            self._pending += view[:take]
            view = view[take:]
            if len(self._pending) < self._need:
                return
            unit, self._pending = self._pending, bytearray()
            self._consume(memoryview(unit))  # exactly one unit: consumed whole
        if not view:
            return
        used = self._consume(view)
        if used < len(view):
            if self.done:
                raise StreamError(f"{len(view) - used} bytes of trailing data after the stream")
            self._pending = bytearray(view[used:])

    def _consume(self, data: memoryview) -> int:
        """Read the header if not yet read, then run; returns the bytes used."""
        pos = 0
        if self.header is None:
            if len(data) < HEADER.size:
                return 0
            self._start(Header.unpack(bytes(data[: HEADER.size])))
            pos = HEADER.size
        return pos + self._run(data[pos:])

    def _start(self, header: Header) -> None:
        s = self._schedule
        header.check(s.n_and, s.n_inputs, len(s.output_slots))
        self.header = header
        self._bytes_per_and = BYTES_PER_AND[header.scheme]
        self._kernel = HalfGates(header.key, header.block_gates)
        self._outputs = AndOutputs(self._labels, self._slots, header.block_gates)

    def _run(self, data: memoryview) -> int:
        """Run steps while the data holds the next block; returns the bytes consumed."""
        kernel, outputs, labels, slots = self._kernel, self._outputs, self._labels, self._slots
        block, per_and, scratch = self.header.block_gates, self._bytes_per_and, self._scratch
        steps, size, pos = self._steps, len(data), 0
        while self._step < len(steps):
            step = steps[self._step]
            if not isinstance(step, AndPlan):
                step.run(labels, slots, scratch)
                self._step += 1
                continue
            k = self._done_in_step
            m = min(block, step.n - k)
            if size - pos < per_and * m:
                self._need = per_and * m
                break
            tables = np.frombuffer(data, np.uint64, 4 * m, pos).reshape(2 * m, 2)
            kernel.evaluate(labels, part(step.a, k, m), part(step.b, k, m), step.first + k,
                            tables, outputs.target(step, k, m))
            outputs.store(step, k, m)
            pos += per_and * m
            if k + m < step.n:
                self._done_in_step = k + m
            else:
                self._done_in_step = 0
                self._step += 1
        return pos


def evaluate_stream(schedule: Schedule, input_labels: np.ndarray, frames) -> np.ndarray:
    """Feed every frame of an iterable stream; return the active output labels."""
    ev = Evaluator(schedule, input_labels)
    for frame in frames:
        ev.feed(frame)
    return ev.output_labels()
