"""The garbler's failpoints do what their names say (snail_garbler/cheats.py): each cheat
is checked on a circuit small enough to read its truth table, garbled and evaluated for
real; the audits' tests (test_audits_e2e.py) run them in the daemons."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from snail_common import failpoints
from snail_common.circuit import CircuitBuilder, schedule_circuit
from snail_common.gc import (
    Evaluator,
    Garbler,
    active_input_labels,
    decode_output_labels,
    fresh_delta,
    fresh_seed,
)
from snail_garbler import cheats


def _run(schedule, garbler_class, bits, scheme="halfgates") -> np.ndarray:
    seed, delta, key = fresh_seed(), fresh_delta(), bytes(16)
    garbler = garbler_class(schedule, seed, delta, key, block_gates=4, scheme=scheme)
    ev = Evaluator(schedule, active_input_labels(seed, delta, np.asarray(bits, bool)))
    for frame in garbler.frames():
        ev.feed(frame)
    return decode_output_labels(delta, garbler.output_zero_labels, ev.output_labels())


def _and_and_not():
    b = CircuitBuilder()
    x = b.input("x", 3, 1)[:, 0]
    b.output("y", b.and_(x[:1], x[1:2]))  # AND gate 0
    b.output("z", b.and_(x[1:2], x[2:3]))  # another AND gate
    b.output("w", b.not_(x[2:3]))
    return schedule_circuit(b.build())


@pytest.mark.parametrize("scheme", ["halfgates", "threehalves"])
def test_and_as_or_garbles_gate_0_as_or_with_valid_labels(scheme):
    schedule = _and_and_not()
    for bits in itertools.product([0, 1], repeat=3):
        a, b, c = bits
        honest = _run(schedule, Garbler, bits, scheme)
        cheat = _run(schedule, cheats._AndAsOr, bits, scheme)
        assert list(honest) == [a & b, b & c, 1 - c]
        assert list(cheat) == [a | b, b & c, 1 - c]  # decodes: every label is valid


def test_stale_circuit_drops_the_not_gates_with_valid_labels():
    schedule = _and_and_not()
    for bits in itertools.product([0, 1], repeat=3):
        a, b, c = bits
        assert list(_run(schedule, cheats._Stale, bits)) == [a & b, b & c, c]


def test_table_bit_flips_the_first_table_frame_only():
    frames = [b"H" * 40, bytes(2000), bytes(100)]
    out = list(cheats._flip_table_bits(iter(frames)))
    assert out[0] == frames[0] and out[2] == frames[2]
    flipped = np.flatnonzero(np.frombuffer(out[1], np.uint8))
    assert list(flipped) == list(range(0, 64 * 16, 16))


def test_nothing_changes_unless_armed():
    failpoints.configure("garbler", {})
    schedule = _and_and_not()
    garbler = Garbler(schedule, fresh_seed(), fresh_delta(), bytes(16))
    stream, chosen = cheats.frames(garbler, {"circuit": "unused"})
    assert chosen is garbler
    list(stream)
    labels = garbler.output_zero_labels
    assert cheats.zero_labels(labels, {"circuit": "unused"}) is labels
