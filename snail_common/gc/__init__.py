"""Garbling engine: half-gates with free-XOR and point-and-permute over a circuit Schedule.

The client derives input labels from (seed, D); the garbler streams tables; the evaluator
consumes them frame by frame; the client decodes (and catches tampering).
"""

from .decode import IntegrityError, decode_output_labels
from .evaluator import Evaluator, evaluate_stream
from .garbler import Garbler
from .labels import (
    active_input_labels,
    check_delta,
    derive_zero_labels,
    fresh_delta,
    fresh_seed,
    labels_from_bytes,
    labels_to_bytes,
)
from .run import garbled_run
from .stream import FRAME_BYTES, Header, StreamError

__all__ = ["FRAME_BYTES", "Evaluator", "Garbler", "Header", "IntegrityError", "StreamError",
           "active_input_labels", "check_delta", "decode_output_labels", "derive_zero_labels",
           "evaluate_stream", "fresh_delta", "fresh_seed", "garbled_run", "labels_from_bytes",
           "labels_to_bytes"]
