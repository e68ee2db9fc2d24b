"""Tampering is caught: a modified table or output label never decodes to a wrong answer."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_gc_garbled import random_circuits

from snail_common.circuit import CircuitBuilder, evaluate_bits, schedule_circuit
from snail_common.gc import (
    Evaluator,
    Garbler,
    IntegrityError,
    StreamError,
    active_input_labels,
    decode_output_labels,
    fresh_delta,
    fresh_seed,
)
from snail_common.gc.stream import HEADER, MAX_BLOCK_GATES, Header


def garble(schedule, bits, **kw):
    seed, delta = fresh_seed(), fresh_delta()
    garbler = Garbler(schedule, seed, delta, **kw)
    frames = list(garbler.frames())
    return seed, delta, garbler, frames[0], bytearray(b"".join(frames[1:]))


def evaluate(schedule, seed, delta, bits, header, tables):
    ev = Evaluator(schedule, active_input_labels(seed, delta, bits))
    ev.feed(header)
    ev.feed(bytes(tables))
    return ev.output_labels()


def one_and_layer(n):
    b = CircuitBuilder()
    x = b.input("x", 2 * n, 1)[:, 0]
    b.output("y", b.and_(x[:n], x[n:]))
    return schedule_circuit(b.build())


def test_flipped_table_bit_is_caught_exactly_when_used():
    """Gate i's TG is used iff the evaluator's select bit of a is 1 (TE: of b); a used,
    flipped ciphertext bit shifts the output label off both valid values."""
    n = 16
    schedule = one_and_layer(n)
    rng = np.random.default_rng(5)
    caught = 0
    for _ in range(4):
        bits = rng.integers(0, 2, 2 * n).astype(bool)
        seed, delta, garbler, header, tables = garble(schedule, bits)
        active = active_input_labels(seed, delta, bits)
        step = schedule.steps()[0]
        sel_a = active[step.a, 0] & np.uint64(1)
        sel_b = active[step.b, 0] & np.uint64(1)
        for gate in range(n):
            for half, used in ((0, sel_a[gate]), (1, sel_b[gate])):
                bad = tables.copy()
                bit = int(rng.integers(0, 128))
                bad[16 * (half * n + gate) + bit // 8] ^= 1 << (bit % 8)
                out = evaluate(schedule, seed, delta, bits, header, bad)
                if used:
                    caught += 1
                    with pytest.raises(IntegrityError):
                        decode_output_labels(delta, garbler.output_zero_labels, out)
                else:
                    got = decode_output_labels(delta, garbler.output_zero_labels, out)
                    assert np.array_equal(got, bits[:n] & bits[n:])
    assert caught > 20


@settings(max_examples=40, deadline=None)
@given(circuit=random_circuits(), where=st.integers(0, 2**40), bit=st.integers(0, 7))
def test_any_flipped_bit_never_decodes_wrong(circuit, where, bit):
    schedule = schedule_circuit(circuit)
    bits = np.random.default_rng(where % 1000).integers(0, 2, circuit.n_inputs).astype(bool)
    seed, delta, garbler, header, tables = garble(schedule, bits)
    expect = evaluate_bits(schedule, bits[None])[0]
    stream = bytearray(header) + tables
    pos = where % len(stream)
    stream[pos] ^= 1 << bit
    try:
        out = evaluate(schedule, seed, delta, bits, stream[: len(header)],
                       stream[len(header) :])
        got = decode_output_labels(delta, garbler.output_zero_labels, out)
    except (IntegrityError, StreamError):
        return
    assert np.array_equal(got, expect)


def test_flipped_key_byte_is_caught():
    schedule = one_and_layer(8)
    bits = np.ones(16, bool)
    seed, delta, garbler, header, tables = garble(schedule, bits)
    bad = bytearray(header)
    bad[HEADER.size - 1] ^= 0x80  # last byte of the AES key
    out = evaluate(schedule, seed, delta, bits, bytes(bad), tables)
    with pytest.raises(IntegrityError):
        decode_output_labels(delta, garbler.output_zero_labels, out)


@settings(max_examples=30, deadline=None)
@given(circuit=random_circuits(), which=st.integers(0, 2**32), bit=st.integers(0, 127))
def test_tampered_output_label(circuit, which, bit):
    schedule = schedule_circuit(circuit)
    bits = np.zeros(circuit.n_inputs, bool)
    seed, delta, garbler, header, tables = garble(schedule, bits)
    out = evaluate(schedule, seed, delta, bits, header, tables)
    decode_output_labels(delta, garbler.output_zero_labels, out)  # the honest run decodes
    out[which % len(out), bit // 64] ^= np.uint64(1) << np.uint64(bit % 64)
    with pytest.raises(IntegrityError):
        decode_output_labels(delta, garbler.output_zero_labels, out)


def test_decode_rejects_mismatched_shapes():
    d = fresh_delta()
    with pytest.raises(IntegrityError):
        decode_output_labels(d, np.zeros((3, 2), np.uint64), np.zeros((2, 2), np.uint64))


def test_stream_errors():
    schedule = one_and_layer(4)
    bits = np.zeros(8, bool)
    seed, delta, _garbler, header, tables = garble(schedule, bits)
    labels = active_input_labels(seed, delta, bits)
    for pos, value in ((0, ord("X")), (4, 99), (5, 77)):  # magic, version, scheme
        bad = bytearray(header)
        bad[pos] = value
        with pytest.raises(StreamError):
            Evaluator(schedule, labels).feed(bytes(bad))
    with pytest.raises(StreamError, match="AND"):  # a stream for another circuit
        Evaluator(one_and_layer(5), active_input_labels(seed, delta, np.zeros(10, bool))
                  ).feed(header)
    ev = Evaluator(schedule, labels)
    ev.feed(header + tables[:-1])
    with pytest.raises(StreamError, match="ended"):
        ev.output_labels()
    ev = Evaluator(schedule, labels)
    with pytest.raises(StreamError, match="trailing"):
        ev.feed(header + tables + b"x")
    with pytest.raises(ValueError):
        Evaluator(schedule, labels[:-1])
    with pytest.raises(RuntimeError):
        Garbler(schedule, seed, delta).output_zero_labels  # noqa: B018


def test_header_and_garbler_arguments_are_bounded():
    """A stream header cannot make the evaluator allocate without bound; bad garbler
    arguments fail at construction, not after the header went out."""
    schedule = one_and_layer(4)
    seed, delta = fresh_seed(), fresh_delta()
    header = Header(schedule.n_and, 8, 4, MAX_BLOCK_GATES + 1, bytes(16))
    with pytest.raises(StreamError, match="block size"):
        Evaluator(schedule, active_input_labels(seed, delta, np.zeros(8, bool))).feed(
            header.pack())
    for kw in ({"block_gates": 0}, {"block_gates": MAX_BLOCK_GATES + 1}, {"key": bytes(15)}):
        with pytest.raises(ValueError):
            Garbler(schedule, seed, delta, **kw)
