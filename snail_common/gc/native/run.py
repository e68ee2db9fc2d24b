"""One garbled or evaluated run on the native kernel: ranges of program ops per call.

A caller holds a ``NativeRun`` per run and asks it for op ranges that fit a buffer of
tables (``fit``): the garbler fills a frame per call, the evaluator runs what the bytes
received so far allow. Every call checks its range and its buffers' shapes and sizes
against the program (whose indices program.py has checked), so the kernel never reads
or writes outside them, whatever arrives from the wire.
"""

from __future__ import annotations

import ctypes
import os
import threading

import numpy as np

from snail_common.circuit.memo import per_object
from snail_common.circuit.plan import plan_for
from snail_common.circuit.schedule import Schedule

from ..stream import KEY_BYTES, SCHEME_HALF_GATES
from .build import library
from .program import Program, build_program, ops_within

U64 = np.uint64
GARBLE, EVALUATE = 0, 1
MAX_LANES = 256  # kernel.c's MAX_LANES
MAX_THREADS = 2  # kernel.c's MAX_THREADS
THREADS_ENV = "SNAIL_KERNEL_THREADS"
BLOCK_SIZES_KEPT = 4  # programs kept per schedule (the block size comes from a stream header)
_programs = per_object(lambda schedule: {})
_lock = threading.Lock()


def program_for(schedule: Schedule, block: int) -> Program:
    """The kernel program of ``schedule``'s plan with blocks of ``block`` gates, built and
    checked once while the schedule lives (the last BLOCK_SIZES_KEPT block sizes)."""
    per_block = _programs(schedule)
    with _lock:
        program = per_block.get(block)
    if program is None:
        program = build_program(plan_for(schedule), schedule.n_slots, block)
        with _lock:
            per_block[block] = program
            while len(per_block) > BLOCK_SIZES_KEPT:
                del per_block[next(iter(per_block))]
    return program


def kernel_threads(threads: int | None = None) -> int:
    """Threads a run may cut its wide ops across: ``threads``, else $SNAIL_KERNEL_THREADS,
    else 1 (a daemon serves many sessions at once: one core each by default)."""
    raw = threads if threads is not None else os.environ.get(THREADS_ENV) or 1
    source = "threads" if threads is not None else THREADS_ENV
    try:
        value = int(raw)
    except ValueError:
        value = 0
    if not 1 <= value <= MAX_THREADS:
        raise ValueError(f"{source} must be an integer in 1..{MAX_THREADS}, got {raw!r}")
    return value


def _pointer(arr: np.ndarray | None) -> int | None:
    return None if arr is None else arr.ctypes.data


class NativeRun:
    """Garbling (``deltas`` given) or evaluation of one run of ``schedule`` on ``values``
    (n_slots, 2L): L lanes, one AES key each; three-halves (one lane) garbling needs
    ``random_key``. Wide ops run on ``threads`` cores (``kernel_threads``)."""

    def __init__(self, schedule: Schedule, block: int, scheme: int, values: np.ndarray,
                 keys: list[bytes], deltas: np.ndarray | None = None,
                 random_key: bytes | None = None, threads: int | None = None) -> None:
        self._lib = library()
        self.threads = kernel_threads(threads)
        lanes = len(keys)
        if not 1 <= lanes <= MAX_LANES or any(len(k) != KEY_BYTES for k in keys):
            raise ValueError(f"need 1..{MAX_LANES} keys of {KEY_BYTES} bytes")
        if scheme != SCHEME_HALF_GATES and lanes != 1:
            raise ValueError("lanes run half-gates only")
        self.program = program_for(schedule, block)
        if (values.dtype != U64 or not values.flags.c_contiguous or not values.flags.writeable
                or values.shape != (self.program.n_slots, 2 * lanes)):
            raise ValueError(f"values must be a writable contiguous uint64 array of shape "
                             f"{(self.program.n_slots, 2 * lanes)}, got {values.dtype} "
                             f"{values.shape}")
        self._mode = EVALUATE if deltas is None else GARBLE
        if deltas is not None:
            deltas = np.ascontiguousarray(deltas, U64).reshape(-1, 2)
            if len(deltas) != lanes:
                raise ValueError(f"need {lanes} offsets, got {len(deltas)}")
        if self._mode == GARBLE and scheme != SCHEME_HALF_GATES and (
                random_key is None or len(random_key) != KEY_BYTES):
            raise ValueError("three-halves garbling needs the key of its random bits")
        self._scheme, self._lanes, self._values = scheme, lanes, values
        self._keys = b"".join(bytes(k) for k in keys)
        self._deltas = deltas
        self._random = bytes(random_key) if random_key is not None and self._mode == GARBLE \
            else None
        self._scratch = np.empty((max(self.program.scratch_rows, 1), 2 * lanes), U64)
        self.cum = self.program.table_words(scheme)  # table words before each op
        self._empty = np.empty((lanes, 1), U64)
        self.pos = 0  # the next op to run

    @property
    def done(self) -> bool:
        return self.pos == self.program.n_ops

    def next_words(self) -> int:
        """Table words (per lane) the next op with tables needs: 0 once none is left."""
        if self.done:
            return 0
        end = ops_within(self.cum, self.pos, 0)
        return 0 if end == self.program.n_ops else int(self.cum[end + 1] - self.cum[end])

    def fit(self, words: int) -> tuple[int, int]:
        """(end, table words) of the longest range from the next op whose tables take at
        most ``words`` per lane."""
        end = ops_within(self.cum, self.pos, words)
        return end, int(self.cum[end] - self.cum[self.pos])

    def run(self, end: int, tables: np.ndarray | None) -> None:
        """Run ops pos .. end-1 with their tables: ``tables`` (L, >= words) uint64, rows
        contiguous (written when garbling, read when evaluating)."""
        lo, words = self.pos, int(self.cum[end] - self.cum[self.pos])
        if not lo <= end <= self.program.n_ops:
            raise ValueError(f"op range {lo}..{end} outside 0..{self.program.n_ops}")
        if tables is None or words == 0:
            tables = self._empty
        if (tables.dtype != U64 or tables.ndim != 2 or tables.shape[0] != self._lanes
                or tables.shape[1] < words or tables.strides[1] != 8
                or tables.strides[0] % 8 or tables.strides[0] < 8 * tables.shape[1]):
            raise ValueError(f"tables must be uint64 ({self._lanes}, >= {words}) with "
                             f"contiguous rows, got {tables.dtype} {tables.shape}")
        if self._mode == GARBLE and not tables.flags.writeable:
            raise ValueError("a garbling run needs writable tables")
        p = self.program
        rc = self._lib.snail_run(
            self._mode, self._scheme, p.ops.ctypes.data, lo, end, p.rows.ctypes.data,
            self._values.ctypes.data, self._lanes, self._scratch.ctypes.data,
            tables.ctypes.data, tables.strides[0] // 8,
            ctypes.c_char_p(self._keys), _pointer(self._deltas),
            None if self._random is None else ctypes.c_char_p(self._random), self.threads)
        if rc:
            raise RuntimeError(f"the native kernel refused its arguments (code {rc})")
        self.pos = end
