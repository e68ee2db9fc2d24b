"""Cleartext evaluation over a Schedule: the test oracle for every garbled run.

Runs 64 input vectors per uint64 word (bit-packed lanes), so one pass over the schedule
evaluates many inputs at once. It is the schedule runner (runner.py) with a bitwise AND
as its AND kernel: the same plan, the same loop as garbling and evaluation.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from .ir import FIRST_INPUT, Circuit, Interface
from .plan import plan_for
from .runner import drain, run_plan
from .schedule import Schedule
from .slots import Rows, gather
from .values import from_bits, pack_lanes, to_bits, unpack_lanes


class _BitAnd:
    """The cleartext AND kernel: out = values[a] & values[b] on packed lanes."""

    def __init__(self, block: int, width: int) -> None:
        self._a = np.empty((block, width), np.uint64)
        self._b = np.empty((block, width), np.uint64)

    def __call__(self, values: np.ndarray, a: Rows, b: Rows, gate0: int, out: np.ndarray,
                 tables: None) -> None:
        np.bitwise_and(gather(values, a, self._a), gather(values, b, self._b), out=out)


def run_schedule(schedule: Schedule, input_words: np.ndarray) -> np.ndarray:
    """Evaluate on packed lanes: uint64 (n_inputs, W) -> uint64 (n_outputs, W)."""
    width = input_words.shape[1] if input_words.ndim == 2 else 1
    plan = plan_for(schedule, strided=width == 1)
    values = np.empty((schedule.n_slots, width), np.uint64)
    values[0] = 0
    values[1] = np.uint64(0xFFFFFFFFFFFFFFFF)
    values[FIRST_INPUT : FIRST_INPUT + schedule.n_inputs] = input_words.reshape(
        schedule.n_inputs, width)
    block = max(plan.max_and_step, 1)  # one block per AND step: no yield per block
    drain(run_plan(plan, values, _BitAnd(block, width), block))
    return values[schedule.output_slots]


def evaluate_bits(schedule: Schedule, input_bits: np.ndarray) -> np.ndarray:
    """bool (L, n_inputs) -> bool (L, n_outputs): one row per input vector."""
    input_bits = np.atleast_2d(np.asarray(input_bits, dtype=bool))
    lanes = input_bits.shape[0]
    out = run_schedule(schedule, pack_lanes(input_bits.T))
    return unpack_lanes(out, lanes).T


def encode_inputs(circuit: Circuit | Interface, values: Mapping[str, object],
                  batch: int | None = None) -> np.ndarray:
    """Named input values -> bool (L, n_inputs); with ``batch`` every value has a leading
    batch axis of that length."""
    missing = [g.name for g in circuit.inputs if g.name not in values]
    extra = sorted(set(values) - {g.name for g in circuit.inputs})
    if missing or extra:
        raise ValueError(f"inputs missing {missing} / unknown {extra}")
    lanes = 1 if batch is None else batch
    parts = []
    for g in circuit.inputs:
        v = np.asarray(values[g.name], dtype=object if g.dtype == "int" else g.dtype)
        want = g.shape if batch is None else (batch, *g.shape)
        if v.shape != want:
            raise ValueError(f"input {g.name!r} has shape {v.shape}, expected {want}")
        parts.append(to_bits(v, g.bits, g.dtype).reshape(lanes, -1))
    return np.concatenate(parts, axis=1) if parts else np.zeros((lanes, 0), bool)


def decode_outputs(circuit: Circuit | Interface, bits: np.ndarray,
                   batch: bool = False) -> dict[str, np.ndarray]:
    """bool (L, n_outputs) -> named output values (leading batch axis if ``batch``)."""
    bits = np.atleast_2d(bits)
    out, pos = {}, 0
    for g in circuit.output_groups:
        chunk = bits[:, pos : pos + g.size].reshape((bits.shape[0], *g.shape, g.bits))
        pos += g.size
        vals = from_bits(chunk, g.dtype)
        out[g.name] = vals if batch else vals[0]
    return out


def evaluate(circuit: Circuit, values: Mapping[str, object], schedule: Schedule | None = None,
             batch: int | None = None) -> dict[str, np.ndarray]:
    """Evaluate a circuit in the clear on named, typed inputs."""
    from .schedule import schedule_circuit

    sched = schedule if schedule is not None else schedule_circuit(circuit)
    bits = evaluate_bits(sched, encode_inputs(circuit, values, batch))
    return decode_outputs(circuit, bits, batch=batch is not None)
