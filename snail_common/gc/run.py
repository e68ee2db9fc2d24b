"""All three roles in one process: the reference path for tests and ``snail-bench``."""

from __future__ import annotations

import numpy as np

from snail_common.circuit.schedule import Schedule

from .decode import decode_output_labels
from .evaluator import evaluate_stream
from .garbler import Garbler
from .labels import active_input_labels, fresh_delta, fresh_seed
from .stream import DEFAULT_SCHEME


def garbled_run(schedule: Schedule, input_bits: np.ndarray,
                scheme: str = DEFAULT_SCHEME) -> np.ndarray:
    """Garble, evaluate and decode with a fresh seed and offset: bool (n_inputs,) ->
    bool (n_outputs,); a batch (L, n_inputs) -> (L, n_outputs), one garbled run per row."""
    bits = np.asarray(input_bits, dtype=bool)
    if bits.ndim == 2:
        return np.array([garbled_run(schedule, row, scheme) for row in bits],
                        dtype=bool).reshape(
            len(bits), len(schedule.output_slots))
    if bits.shape != (schedule.n_inputs,):
        raise ValueError(f"expected {schedule.n_inputs} input bits, got shape {bits.shape}")
    seed, delta = fresh_seed(), fresh_delta()
    garbler = Garbler(schedule, seed, delta, scheme=scheme)
    active = evaluate_stream(schedule, active_input_labels(seed, delta, bits), garbler.frames())
    return decode_output_labels(delta, garbler.output_zero_labels, active)
