"""Compiler benchmark: build, schedule and evaluate a ~50 M gate circuit in the clear.

The workload is many independent 32x32-bit shift-and-add multipliers side by side
(ripple-carry adders, 1 AND per bit): wide like the per-point work of localization,
with about a thousand AND levels.
"""

from __future__ import annotations

import resource
import time

import numpy as np

from snail_common.circuit import CircuitBuilder, run_schedule, schedule_circuit
from snail_common.circuit.builder import WireArray

GATES_PER_MULTIPLIER = 2915  # measured: 32x32 -> 32-bit shift-and-add multiplier


def _ripple_add(b: CircuitBuilder, x: WireArray, y: WireArray) -> WireArray:
    """x + y mod 2^bits along the last axis; carry c' = c ^ ((x ^ c) & (y ^ c))."""
    carry = np.zeros(x.shape[:-1], np.int32)
    out = np.empty_like(x)
    for i in range(x.shape[-1]):
        t = b.xor(x[..., i], carry)
        out[..., i] = b.xor(t, y[..., i])
        carry = b.xor(carry, b.and_(t, b.xor(y[..., i], carry)))
    return out


def build_multipliers(count: int):
    b = CircuitBuilder()
    x = b.input("x", (count,), 32, "uint32")
    y = b.input("y", (count,), 32, "uint32")
    acc = b.and_(x, y[:, :1])
    for i in range(1, 32):
        partial = b.and_(x[:, : 32 - i], y[:, i : i + 1])
        shifted = np.concatenate([np.zeros((count, i), np.int32), partial], axis=1)
        acc = _ripple_add(b, acc, shifted)
    b.output("p", acc, "uint32")
    return b.build()


def compiler_report(gates: int = 50_000_000, lanes_words: int = 1) -> dict:
    """Build + schedule time, peak RSS and cleartext gate rate for a circuit of ~``gates``."""
    count = max(1, gates // GATES_PER_MULTIPLIER)
    t0 = time.perf_counter()
    circuit = build_multipliers(count)
    t1 = time.perf_counter()
    schedule = schedule_circuit(circuit)
    t2 = time.perf_counter()
    rng = np.random.default_rng(0)
    words = rng.integers(0, 2**63, size=(circuit.n_inputs, lanes_words), dtype=np.uint64)
    t3 = time.perf_counter()
    run_schedule(schedule, words)
    t4 = time.perf_counter()
    peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return {"compiler": {
        "gates": circuit.n_gates, **circuit.counts(), "depth": circuit.depth(),
        "steps": schedule.n_steps, "peak_slots": schedule.n_slots,
        "build_s": round(t1 - t0, 3), "schedule_s": round(t2 - t1, 3),
        "build_and_schedule_s": round(t2 - t0, 3), "peak_rss_bytes": peak_rss,
        "cleartext_s": round(t4 - t3, 3), "lanes": 64 * lanes_words,
        "cleartext_gates_per_s": round(circuit.n_gates / (t4 - t3)),
    }}
