"""Compiler benchmark: build, schedule and evaluate a ~50 M gate circuit in the clear.

The workload is many independent 32x32-bit shift-and-add multipliers side by side
(ripple-carry adders, 1 AND per bit): wide like the per-point work of localization
(17 k multipliers at 50 M gates, AND-depth 32).

The cleartext evaluator plans a schedule once (strided runs, see cleartext.py); the
first run pays for that and for first-touching the slot memory, so the gate rate is
taken from a second run: one pass, each gate counted once however many lanes.
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


def _check_products(count: int, words: np.ndarray, out: np.ndarray) -> None:
    """The first and last lane of the first word must hold x * y mod 2^32 per multiplier."""
    weights = np.uint64(1) << np.arange(32, dtype=np.uint64)
    for lane in (0, 63):
        bits = (words[:, 0] >> np.uint64(lane)) & np.uint64(1)
        x, y = (b.reshape(count, 32) @ weights for b in np.split(bits, 2))
        p = ((out[:, 0] >> np.uint64(lane)) & np.uint64(1)).reshape(count, 32) @ weights
        if not np.array_equal(p, (x * y) & np.uint64(0xFFFFFFFF)):
            raise RuntimeError(f"cleartext products wrong in lane {lane}")


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
    first = run_schedule(schedule, words)
    t4 = time.perf_counter()
    again = run_schedule(schedule, words)
    t5 = time.perf_counter()
    _check_products(count, words, first)
    if not np.array_equal(first, again):
        raise RuntimeError("cleartext runs on the same inputs disagree")
    peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return {"compiler": {
        "gates": circuit.n_gates, **circuit.counts(), "depth": circuit.depth(),
        "steps": schedule.n_steps, "peak_slots": schedule.n_slots,
        "build_s": round(t1 - t0, 3), "schedule_s": round(t2 - t1, 3),
        "build_and_schedule_s": round(t2 - t0, 3), "peak_rss_bytes": peak_rss,
        "cleartext_first_s": round(t4 - t3, 3), "cleartext_s": round(t5 - t4, 3),
        "lanes": 64 * lanes_words, "cleartext_gates_per_s": round(circuit.n_gates / (t5 - t4)),
    }}
