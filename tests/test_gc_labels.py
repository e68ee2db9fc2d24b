"""Label PRG and client-side label derivation."""

import numpy as np
import pytest

from snail_common.circuit import CircuitBuilder, schedule_circuit
from snail_common.gc import (
    Garbler,
    active_input_labels,
    check_delta,
    derive_zero_labels,
    fresh_delta,
    fresh_seed,
    labels_from_bytes,
    labels_to_bytes,
)


def test_zero_labels_are_aes_ctr_known_answer():
    # AES-128 with the all-zero key on the all-zero block (FIPS-197 style known answer)
    first = labels_to_bytes(derive_zero_labels(bytes(16), 1))
    assert first.hex() == "66e94bd4ef8a2c3b884cfa59ca342b2e"


def test_zero_labels_are_a_prefix_stream_and_depend_on_seed():
    seed = bytes(range(16))
    long = derive_zero_labels(seed, 100)
    assert np.array_equal(derive_zero_labels(seed, 7), long[:7])
    assert len(np.unique(long, axis=0)) == 100
    other = derive_zero_labels(bytes(range(1, 17)), 100)
    assert not np.any((other == long).all(axis=1))
    assert derive_zero_labels(seed, 0).shape == (0, 2)


def test_bad_seed_length():
    with pytest.raises(ValueError):
        derive_zero_labels(bytes(15), 3)


def test_fresh_values():
    assert len(fresh_seed()) == 16 and fresh_seed() != fresh_seed()
    deltas = [fresh_delta() for _ in range(20)]
    assert all(d.dtype == np.uint64 and d.shape == (2,) and int(d[0]) & 1 for d in deltas)
    assert len({labels_to_bytes(d) for d in deltas}) == 20


def test_check_delta():
    d = np.array([5, 7], np.uint64)
    assert check_delta(d) is d
    assert np.array_equal(check_delta(labels_to_bytes(d)), d)
    with pytest.raises(ValueError, match="lowest bit"):
        check_delta(np.array([4, 7], np.uint64))
    with pytest.raises(ValueError):
        check_delta(np.array([5, 7, 9], np.uint64))


def test_label_bytes_round_trip():
    x = derive_zero_labels(fresh_seed(), 9)
    assert np.array_equal(labels_from_bytes(labels_to_bytes(x)), x)
    with pytest.raises(ValueError):
        labels_from_bytes(b"123")


def test_active_labels_follow_bits():
    seed, delta = fresh_seed(), fresh_delta()
    bits = np.array([1, 0, 0, 1, 1], bool)
    zero = derive_zero_labels(seed, 7)
    active = active_input_labels(seed, delta, bits)
    assert np.array_equal(active[0], zero[0])  # constant 0
    assert np.array_equal(active[1], zero[1] ^ delta)  # constant 1
    for i, bit in enumerate(bits):
        assert np.array_equal(active[2 + i], zero[2 + i] ^ (delta if bit else 0))


def test_client_labels_equal_garbler_input_labels():
    b = CircuitBuilder()
    x = b.input("x", 12, 1)
    b.output("y", b.and_(x[:6], x[6:]))
    schedule = schedule_circuit(b.build())
    seed, delta = fresh_seed(), fresh_delta()
    garbler = Garbler(schedule, seed, delta)
    bits = np.random.default_rng(3).integers(0, 2, 12).astype(bool)
    client = active_input_labels(seed, delta, bits)
    g0 = garbler.input_zero_labels
    assert g0.shape == (14, 2)
    expect = g0 ^ np.where(np.concatenate([[0, 1], bits])[:, None], delta, 0).astype(np.uint64)
    assert np.array_equal(client, expect)
