"""Garbled runs decode to exactly the cleartext evaluation of the same schedule."""

import itertools
import tracemalloc
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shared_paths import BRISTOL

from snail_common.circuit import CircuitBuilder, evaluate_bits, schedule_circuit
from snail_common.circuit.bristol import load_bristol
from snail_common.circuit.plan import AndPlan, _ReadRows, plan_for
from snail_common.circuit.schedule import Schedule
from snail_common.gc import (
    Evaluator,
    Garbler,
    active_input_labels,
    decode_output_labels,
    fresh_delta,
    fresh_seed,
    garbled_run,
)
from snail_common.gc.native.run import program_for


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


SCHEMES = ("halfgates", "threehalves")


@settings(max_examples=60, deadline=None)
@given(circuit=random_circuits(), block=st.sampled_from([1, 2, 3, 7, 4096]),
       reuse=st.booleans(), scheme=st.sampled_from(SCHEMES), data=st.data())
def test_random_circuits_match_cleartext(circuit, block, reuse, scheme, data):
    schedule = schedule_circuit(circuit, reuse_slots=reuse)
    seed = data.draw(st.integers(0, 2**32 - 1))
    bits = np.random.default_rng(seed).integers(0, 2, (3, circuit.n_inputs)).astype(bool)
    expect = evaluate_bits(schedule, bits)
    for row, want in zip(bits, expect):
        got = run(schedule, row, block_gates=block, frame_bytes=32 * block * 2, scheme=scheme)
        assert np.array_equal(got, want)


@settings(max_examples=25, deadline=None)
@given(circuit=random_circuits(), cuts=st.lists(st.integers(0, 10**6), max_size=12),
       scheme=st.sampled_from(SCHEMES))
def test_stream_cut_anywhere(circuit, cuts, scheme):
    """The evaluator accepts the byte stream split at arbitrary points (socket reads)."""
    schedule = schedule_circuit(circuit)
    bits = np.random.default_rng(len(cuts)).integers(0, 2, circuit.n_inputs).astype(bool)
    seed, delta = fresh_seed(), fresh_delta()
    garbler = Garbler(schedule, seed, delta, block_gates=5, scheme=scheme)
    stream = b"".join(garbler.frames())
    points = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    ev = Evaluator(schedule, active_input_labels(seed, delta, bits))
    for lo, hi in itertools.pairwise(points):
        ev.feed(stream[lo:hi])
    got = decode_output_labels(delta, garbler.output_zero_labels, ev.output_labels())
    assert np.array_equal(got, evaluate_bits(schedule, bits[None])[0])


def test_stream_fed_in_small_reads():
    """Reads much smaller than a block: each cut block is assembled once, then evaluated."""
    schedule = schedule_circuit(wide_and_layers(700, 2))
    bits = np.random.default_rng(9).integers(0, 2, schedule.n_inputs).astype(bool)
    seed, delta = fresh_seed(), fresh_delta()
    garbler = Garbler(schedule, seed, delta, block_gates=256)
    stream = memoryview(b"".join(garbler.frames()))
    ev = Evaluator(schedule, active_input_labels(seed, delta, bits))
    for pos in range(0, len(stream), 1000):
        ev.feed(stream[pos : pos + 1000])
    got = decode_output_labels(delta, garbler.output_zero_labels, ev.output_labels())
    assert np.array_equal(got, evaluate_bits(schedule, bits[None])[0])


def wide_and_layers(count: int, layers: int):
    """``count`` independent lanes of ``layers`` AND levels with XOR logic between them."""
    b = CircuitBuilder()
    x = b.input("x", (count, 4), 1)[..., 0]
    acc = x[:, 0]
    for i in range(1, layers + 1):
        acc = b.and_(b.xor(acc, x[:, i % 4]), b.or_(acc, x[:, (i + 1) % 4]))
    b.output("y", acc[:, None])
    return b.build()


@pytest.mark.parametrize("scheme", SCHEMES)
def test_wide_steps_span_blocks_and_frames(scheme):
    """Steps wider than a block reuse their own operand slots; frames cut between blocks."""
    schedule = schedule_circuit(wide_and_layers(3000, 3))
    bits = np.random.default_rng(7).integers(0, 2, (2, schedule.n_inputs)).astype(bool)
    expect = evaluate_bits(schedule, bits)
    for row, want in zip(bits, expect):
        assert np.array_equal(run(schedule, row, block_gates=1000, frame_bytes=70_000,
                                  scheme=scheme), want)
        assert np.array_equal(garbled_run(schedule, row, scheme), want)


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


# three-halves on every file but the two slow divisions (the others cover their gate mix)
BRISTOL_RUNS = [(p, s) for s in SCHEMES for p in BRISTOL_FILES
                if s == "halfgates" or p.stem not in ("divide64", "udivide64")]


@pytest.mark.parametrize(("path", "scheme"), BRISTOL_RUNS,
                         ids=lambda v: v if isinstance(v, str) else v.stem)
def test_bristol_garbled_matches_cleartext(path, scheme):
    circuit = load_bristol(path)
    schedule = schedule_circuit(circuit)
    rng = np.random.default_rng(zlib.crc32(path.stem.encode()))
    bits = rng.integers(0, 2, (3, circuit.n_inputs)).astype(bool)
    bits[0] = False  # all-zero inputs exercise the constant paths
    assert np.array_equal(garbled_run(schedule, bits, scheme), evaluate_bits(schedule, bits))


def in_place_schedule() -> Schedule:
    """A hand-made schedule whose steps write the very slots they read (an allocator may do
    that: executors read a whole step before writing it), so the plan cannot write as it
    goes. Inputs x0..x5 sit in slots 2..7."""
    and_out = np.array([2, 3, 4, 5, 6, 3, 2], np.int32)  # step 1: 5 gates, step 3: 2 gates
    and_a = np.array([2, 3, 4, 5, 6, 2, 4], np.int32)
    and_b = np.array([7, 6, 5, 4, 3, 3, 3], np.int32)
    lin_out = np.array([4, 5, 7], np.int32)  # step 0 (ragged) and step 2 (2 terms each)
    lin_ptr = np.array([0, 2, 5, 7], np.int64)
    lin_terms = np.array([2, 4, 3, 5, 1, 2, 7], np.int32)
    return Schedule(6, 8, np.array([0, 1, 0, 1], np.uint8), np.array([0, 0, 2, 5], np.int64),
                    np.array([2, 5, 3, 7], np.int64), and_out, and_a, and_b, lin_out, lin_ptr,
                    lin_terms, np.array([2, 3, 4, 5, 7], np.int32))


def test_steps_that_overwrite_their_own_operands():
    schedule = in_place_schedule()
    plan = plan_for(schedule)
    assert not any(step.direct for step in plan.steps if isinstance(step, AndPlan))
    bits = np.random.default_rng(11).integers(0, 2, (16, 6)).astype(bool)
    bits[0] = True
    expect = evaluate_bits(schedule, bits)
    assert len({tuple(row) for row in expect}) > 1
    for row, want in zip(bits, expect):
        for block in (1, 2, 8):
            assert np.array_equal(run(schedule, row, block_gates=block), want)


def contiguous_schedule() -> Schedule:
    """A hand-made schedule whose outputs and some operands are runs of consecutive slots,
    none of them read by the step writing them. Inputs x0..x5 sit in slots 2..7."""
    and_out = np.array([11, 12, 13, 14, 5, 6, 7], np.int32)
    and_a = np.array([8, 9, 10, 2, 2, 3, 4], np.int32)
    and_b = np.array([3, 4, 5, 6, 11, 12, 13], np.int32)
    lin_out = np.array([8, 9, 10, 2, 3, 4], np.int32)
    lin_ptr = np.array([0, 2, 4, 6, 9, 11, 13], np.int64)
    lin_terms = np.array([2, 3, 4, 5, 6, 1, 11, 12, 13, 14, 1, 11, 7], np.int32)
    return Schedule(6, 15, np.array([0, 1, 0, 1], np.uint8), np.array([0, 0, 3, 4], np.int64),
                    np.array([3, 4, 6, 7], np.int64), and_out, and_a, and_b, lin_out, lin_ptr,
                    lin_terms, np.array([5, 6, 7, 14], np.int32))


def test_contiguous_outputs_are_written_in_place():
    schedule = contiguous_schedule()
    lin0, and1, _, and3 = plan_for(schedule).steps
    assert lin0.direct and and1.direct and and3.direct
    assert lin0.groups[0].out == slice(8, 11, 1)
    assert (and1.out, and1.b, and3.out, and3.a, and3.b) == (
        slice(11, 15, 1), slice(3, 7, 1), slice(5, 8, 1), slice(2, 5, 1), slice(11, 14, 1))
    bits = np.random.default_rng(12).integers(0, 2, (16, 6)).astype(bool)
    expect = evaluate_bits(schedule, bits)
    assert len({tuple(row) for row in expect}) > 1
    for row, want in zip(bits, expect):
        for block in (1, 2, 3, 8):
            assert np.array_equal(run(schedule, row, block_gates=block), want)


def test_memory_is_live_slots_plus_a_frame():
    """Garbling and evaluating a long, narrow circuit frame by frame holds its live labels,
    fixed-size scratch and a frame, never the garbled circuit (here 1.2 MB of tables)."""
    schedule = schedule_circuit(wide_and_layers(64, 300))
    plan_for(schedule)  # the plan is per circuit, like the schedule: built before measuring
    program_for(schedule, 64)  # and so is the native kernel's program of it
    seed, delta = fresh_seed(), fresh_delta()
    labels = active_input_labels(seed, delta, np.zeros(schedule.n_inputs, bool))
    tracemalloc.start()
    try:
        garbler = Garbler(schedule, seed, delta, block_gates=64, frame_bytes=4096)
        ev = Evaluator(schedule, labels)
        for frame in garbler.frames():
            ev.feed(frame)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert 32 * schedule.n_and > 1_000_000
    assert peak < 150_000, f"peak {peak} bytes for {schedule.n_slots} slots"


def test_plan_rejects_and_steps_that_would_reuse_tweaks():
    """Every AND gate's number is its hash tweak: steps must tile the AND rows in order."""
    s = contiguous_schedule()
    s.step_lo = np.array([0, 0, 3, 3], np.int64)  # the second AND step repeats gate 3
    with pytest.raises(ValueError, match="tweaks"):
        plan_for(s)


@settings(max_examples=100, deadline=None)
@given(n=st.integers(1, 12), start=st.integers(0, 8), data=st.data())
def test_write_safety_checks_match_their_definition(n, start, data):
    """A step may write block by block iff each out[i] is read only by rows <= i; a linear
    step may write as it goes iff it reads none of its outputs (contiguous or not)."""
    slots = st.integers(0, 24)
    a = np.array(data.draw(st.lists(slots, min_size=n, max_size=n)), np.int32)
    b = np.array(data.draw(st.lists(slots, min_size=n, max_size=n)), np.int32)
    scattered = np.array(data.draw(st.lists(slots, min_size=n, max_size=n, unique=True)),
                         np.int32)
    for out in (np.arange(start, start + n, dtype=np.int32), scattered):
        ordered = all(j <= i for i, s in enumerate(out.tolist())
                      for j in range(n) if s in (a[j], b[j]))
        checks = _ReadRows(25)
        assert checks.reads_precede_writes(out, a, b) == ordered
        assert checks.disjoint(out, a) == (not set(out.tolist()) & set(a.tolist()))
        assert checks.reads_precede_writes(out, a, b) == ordered  # state was reset


def _multi_frame_garbler() -> Garbler:
    b = CircuitBuilder()
    x = b.input("x", 64, 1)[:, 0]
    acc = b.and_(x[:32], x[32:])
    for i in range(20):
        acc = b.and_(acc, b.xor(acc, np.roll(x[:32], i)))
    b.output("y", acc[:, None])
    return Garbler(schedule_circuit(b.build()), bytes(range(16)), bytes([1] + [7] * 15),
                   bytes(range(16, 32)), block_gates=8, frame_bytes=1024)


def test_the_stream_bytes_for_a_fixed_seed_are_unchanged():
    """The garbled-table stream of a fixed seed, offset and key, byte for byte (digest of
    the stream as garbled before frames became views of their arrays)."""
    import hashlib

    frames = list(_multi_frame_garbler().frames())
    assert len(frames) == 22
    assert hashlib.sha256(b"".join(frames)).hexdigest() == (
        "22d4dea606005fb9678bd077b2d4ad4800fafbbf51b2f85e0ef354767d7fb370")


def test_table_frames_are_uncopied_views_that_later_frames_never_overwrite():
    """Each table frame is a byte view of its own array (no copy on its way to TLS), and
    a frame kept while the next ones are garbled keeps its bytes."""
    kept = list(_multi_frame_garbler().frames())
    one_by_one = b"".join(bytes(f) for f in _multi_frame_garbler().frames())
    tables = kept[1:]
    assert all(isinstance(f, memoryview) and f.format == "B" for f in tables)
    assert len({id(f.obj) for f in tables}) == len(tables)
    assert b"".join(kept) == one_by_one
