"""Garbled runs decode to exactly the cleartext evaluation of the same schedule."""

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shared_paths import BRISTOL

from snail_common.circuit import CircuitBuilder, evaluate_bits, schedule_circuit
from snail_common.circuit.bristol import load_bristol
from snail_common.gc import (
    Evaluator,
    Garbler,
    active_input_labels,
    decode_output_labels,
    fresh_delta,
    fresh_seed,
    garbled_run,
)


@st.composite
def random_circuits(draw):
    """Random netlists built through the builder: batches of XOR/AND/NOT/OR/MUX gates on
    randomly chosen earlier wires (constants included), so steps are wide and deep and slots
    get reused."""
    n_inputs = draw(st.integers(1, 12))
    n_ops = draw(st.integers(0, 30))
    width = draw(st.integers(1, 24))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    b = CircuitBuilder()
    pool = [np.array([0, 1], np.int32), b.input("x", n_inputs, 1).ravel()]
    for _ in range(n_ops):
        wires = np.concatenate(pool)
        k = int(rng.integers(1, width + 1))
        x, y, z = (rng.choice(wires, k) for _ in range(3))
        op = rng.integers(0, 5)
        if op == 0:
            out = b.xor(x, y)
        elif op == 1:
            out = b.and_(x, y)
        elif op == 2:
            out = b.not_(x)
        elif op == 3:
            out = b.or_(x, y)
        else:
            out = b.mux(x, y, z)
        pool.append(np.asarray(out).ravel())
    wires = np.concatenate(pool)
    b.output("y", rng.choice(wires, int(rng.integers(1, 16)))[:, None])
    return b.build()


def run(schedule, bits, **garbler_args):
    seed, delta = fresh_seed(), fresh_delta()
    garbler = Garbler(schedule, seed, delta, **garbler_args)
    ev = Evaluator(schedule, active_input_labels(seed, delta, bits))
    for frame in garbler.frames():
        ev.feed(frame)
    assert ev.done
    return decode_output_labels(delta, garbler.output_zero_labels, ev.output_labels())


@settings(max_examples=60, deadline=None)
@given(circuit=random_circuits(), block=st.sampled_from([1, 2, 3, 7, 4096]),
       reuse=st.booleans(), data=st.data())
def test_random_circuits_match_cleartext(circuit, block, reuse, data):
    schedule = schedule_circuit(circuit, reuse_slots=reuse)
    seed = data.draw(st.integers(0, 2**32 - 1))
    bits = np.random.default_rng(seed).integers(0, 2, (3, circuit.n_inputs)).astype(bool)
    expect = evaluate_bits(schedule, bits)
    for row, want in zip(bits, expect):
        got = run(schedule, row, block_gates=block, frame_bytes=32 * block * 2)
        assert np.array_equal(got, want)


@settings(max_examples=25, deadline=None)
@given(circuit=random_circuits(), cuts=st.lists(st.integers(0, 10**6), max_size=12))
def test_stream_cut_anywhere(circuit, cuts):
    """The evaluator accepts the byte stream split at arbitrary points (socket reads)."""
    schedule = schedule_circuit(circuit)
    bits = np.random.default_rng(len(cuts)).integers(0, 2, circuit.n_inputs).astype(bool)
    seed, delta = fresh_seed(), fresh_delta()
    garbler = Garbler(schedule, seed, delta, block_gates=5)
    stream = b"".join(garbler.frames())
    points = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    ev = Evaluator(schedule, active_input_labels(seed, delta, bits))
    for lo, hi in itertools.pairwise(points):
        ev.feed(stream[lo:hi])
    got = decode_output_labels(delta, garbler.output_zero_labels, ev.output_labels())
    assert np.array_equal(got, evaluate_bits(schedule, bits[None])[0])


def test_wide_steps_span_blocks_and_frames():
    """Steps wider than a block reuse their own operand slots; frames cut between blocks."""
    count = 3000
    b = CircuitBuilder()
    x = b.input("x", (count, 4), 1)[..., 0]
    acc = x[:, 0]
    for i in range(1, 4):
        acc = b.and_(b.xor(acc, x[:, i]), b.or_(acc, x[:, (i + 1) % 4]))
    b.output("y", acc[:, None])
    schedule = schedule_circuit(b.build())
    bits = np.random.default_rng(7).integers(0, 2, (2, schedule.n_inputs)).astype(bool)
    expect = evaluate_bits(schedule, bits)
    for row, want in zip(bits, expect):
        assert np.array_equal(run(schedule, row, block_gates=1000, frame_bytes=70_000), want)
        assert np.array_equal(garbled_run(schedule, row), want)


def test_small_steps_share_frames():
    """A deep narrow circuit streams as a handful of frames, not one per step."""
    b = CircuitBuilder()
    x = b.input("x", 64, 1)[:, 0]
    acc = x[0]
    for i in range(1, 64):
        acc = b.and_(acc, b.xor(x[i], acc))
    b.output("y", acc)
    schedule = schedule_circuit(b.build())
    assert schedule.n_steps > 100
    frames = list(Garbler(schedule, fresh_seed(), fresh_delta()).frames())
    assert len(frames) == 2  # header + one frame of 63 tables
    assert len(frames[1]) == 32 * schedule.n_and


def test_linear_only_and_empty_circuits():
    b = CircuitBuilder()
    x = b.input("x", 5, 1)[:, 0]
    b.output("y", np.stack([b.xor(x[0], x[1]), b.not_(x[2]), x[3], b.const(1), b.const(0)]))
    schedule = schedule_circuit(b.build())
    assert schedule.n_and == 0
    for bits in np.random.default_rng(1).integers(0, 2, (4, 5)).astype(bool):
        assert np.array_equal(garbled_run(schedule, bits),
                              [bits[0] ^ bits[1], not bits[2], bits[3], True, False])


def test_garbled_run_batch_and_shape_check():
    b = CircuitBuilder()
    x = b.input("x", 8, 1)[:, 0]
    b.output("y", b.and_(x[:4], x[4:]))
    schedule = schedule_circuit(b.build())
    bits = np.random.default_rng(2).integers(0, 2, (5, 8)).astype(bool)
    assert np.array_equal(garbled_run(schedule, bits), bits[:, :4] & bits[:, 4:])
    with pytest.raises(ValueError):
        garbled_run(schedule, np.zeros(7, bool))


BRISTOL_FILES = sorted(BRISTOL.glob("*.txt"))
BRISTOL_FILES = [p for p in BRISTOL_FILES if not p.name.startswith("LICENSE")]


def test_bristol_files_present():
    assert len(BRISTOL_FILES) >= 16


@pytest.mark.parametrize("path", BRISTOL_FILES, ids=lambda p: p.stem)
def test_bristol_garbled_matches_cleartext(path):
    circuit = load_bristol(path)
    schedule = schedule_circuit(circuit)
    rng = np.random.default_rng(abs(hash(path.stem)) % 2**32)
    bits = rng.integers(0, 2, (3, circuit.n_inputs)).astype(bool)
    bits[0] = False  # all-zero inputs exercise the constant paths
    assert np.array_equal(garbled_run(schedule, bits), evaluate_bits(schedule, bits))
