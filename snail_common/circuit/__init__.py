"""Circuit compiler: IR, vectorized builder, schedule, cleartext evaluator, cache, Bristol."""

from .builder import CircuitBuilder
from .cleartext import decode_outputs, encode_inputs, evaluate, evaluate_bits, run_schedule
from .ir import AND, NOT, ONE, XOR, ZERO, Circuit, Group, Interface
from .schedule import AndStep, LinearStep, Schedule, schedule_circuit

__all__ = ["AND", "NOT", "ONE", "XOR", "ZERO", "AndStep", "Circuit", "CircuitBuilder", "Group",
           "Interface", "LinearStep", "Schedule", "decode_outputs", "encode_inputs", "evaluate",
           "evaluate_bits", "run_schedule", "schedule_circuit"]
