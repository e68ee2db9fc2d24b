"""The evaluator: consumes the garbled-table stream as it arrives and computes active labels.

``feed`` accepts the stream cut anywhere (frames as sent, or arbitrary socket reads); it
runs the schedule as far as the bytes received allow, so evaluation of frame k overlaps
the garbling and transfer of frame k+1: the schedule runner stays suspended before the
first block whose tables have not arrived. Tables are read in place from the caller's
buffer; only a block cut by a read boundary is copied (once) into a pending buffer.
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit.ir import FIRST_INPUT
from snail_common.circuit.plan import plan_for
from snail_common.circuit.runner import first_block, next_block, run_plan
from snail_common.circuit.schedule import Schedule

from .engine import resolve
from .halfgates import HalfGates
from .native.run import NativeRun
from .stream import (
    HEADER,
    SCHEME_HALF_GATES,
    Header,
    StreamError,
    table_view,
    table_words,
)
from .threehalves import ThreeHalves


class Evaluator:
    """Evaluates one run of ``schedule`` from the client's active input labels
    (slots 0 .. n_inputs+1: constant 0, constant 1, then the inputs). With ``scheme``
    (a stream scheme number) a stream garbled under another scheme is refused. ``engine``
    picks the engine (engine.py; either evaluates either's stream)."""

    def __init__(self, schedule: Schedule, input_labels: np.ndarray,
                 scheme: int | None = None, engine: str | None = None) -> None:
        self.engine = resolve(engine)
        s = self._schedule = schedule
        self._expected_scheme = scheme
        inputs = np.asarray(input_labels, dtype=np.uint64)
        if inputs.shape != (FIRST_INPUT + s.n_inputs, 2):
            raise ValueError(f"expected {FIRST_INPUT + s.n_inputs} input labels, "
                             f"got an array of shape {inputs.shape}")
        self._labels = np.empty((s.n_slots, 2), np.uint64)
        self._labels[: len(inputs)] = inputs
        self._need = HEADER.size  # bytes the next unit of work (header or block) takes
        self._pending = bytearray()  # the start of that unit, when a read cut it
        self.header: Header | None = None
        self._run = None  # the suspended schedule run, once the header is read
        self._block: int | None = None  # gates of the block it waits for; None: finished
        self._native: NativeRun | None = None  # the native engine's run instead

    @property
    def done(self) -> bool:
        return self.header is not None and self._block is None

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
        return pos + self._run_blocks(data[pos:])

    def _start(self, header: Header) -> None:
        s = self._schedule
        header.check(s.n_and, s.n_inputs, len(s.output_slots))
        if self._expected_scheme not in (None, header.scheme):
            raise StreamError(f"the stream is garbled with scheme {header.scheme}, the "
                              f"session agreed on {self._expected_scheme}")
        self.header = header
        if self.engine == "native":
            self._native = NativeRun(s, header.block_gates, header.scheme, self._labels,
                                     [header.key])
            self._block = 0  # not finished: _run_blocks runs the ops
            return
        kind = HalfGates if header.scheme == SCHEME_HALF_GATES else ThreeHalves
        kernel = kind(header.key, header.block_gates)
        self._run = run_plan(plan_for(s), self._labels, kernel.evaluate, header.block_gates)
        self._block = first_block(self._run)

    def _run_blocks(self, data: memoryview) -> int:
        """Run blocks while the data holds their tables; returns the bytes consumed."""
        if self._native is not None:
            return self._run_native(data)
        scheme, size, pos = self.header.scheme, len(data), 0
        while self._block is not None:
            m = self._block
            w = table_words(scheme, m)
            if size - pos < 8 * w:
                self._need = 8 * w
                break
            tables = table_view(scheme, np.frombuffer(data, np.uint64, w, pos), m)
            pos += 8 * w
            self._block = next_block(self._run, tables)
        return pos

    def _run_native(self, data: memoryview) -> int:
        """The native engine's _run_blocks: one kernel call for every op the data holds
        the tables of."""
        run = self._native
        end, words = run.fit(len(data) // 8)
        if end > run.pos:
            tables = np.frombuffer(data, np.uint64, words).reshape(1, words) if words else None
            run.run(end, tables)
        if run.done:
            self._block = None
        else:
            self._need = 8 * run.next_words()
        return 8 * words


def evaluate_stream(schedule: Schedule, input_labels: np.ndarray, frames,
                    engine: str | None = None) -> np.ndarray:
    """Feed every frame of an iterable stream; return the active output labels."""
    ev = Evaluator(schedule, input_labels, engine=engine)
    for frame in frames:
        ev.feed(frame)
    return ev.output_labels()
