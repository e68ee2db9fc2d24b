"""Builder folding, depth tracking, values and lanes."""

import numpy as np
import pytest

from snail_common.circuit import ONE, ZERO, CircuitBuilder, evaluate
from snail_common.circuit.builder import CircuitTooLarge, and_gate_limit
from snail_common.circuit.values import from_bits, pack_lanes, to_bits, unpack_lanes


def test_constant_and_equal_operands_fold_without_gates():
    b = CircuitBuilder()
    x = b.input("x", (), 4, "int")
    assert np.array_equal(b.and_(x, ZERO), [0, 0, 0, 0])
    assert np.array_equal(b.and_(x, ONE), x)
    assert np.array_equal(b.xor(x, ZERO), x)
    assert np.array_equal(b.xor(x, x), [0, 0, 0, 0])
    assert np.array_equal(b.and_(x, x), x)
    assert b.n_gates == 0
    b.xor(x, ONE)
    assert b.n_gates == 4  # NOT gates


def test_mixed_constant_batch_folds_per_element():
    b = CircuitBuilder()
    x = b.input("x", (), 3, "int")
    y = b.and_(np.array([x[0], ZERO, ONE]), np.array([x[1], x[2], x[2]]))
    assert y[1] == ZERO and y[2] == x[2]
    assert b.n_gates == 1


def test_depth_tracking():
    b = CircuitBuilder()
    x = b.input("x", (), 4, "int")
    y = b.and_(b.and_(x[0], x[1]), b.xor(x[2], x[3]))
    b.output("y", np.array([y]), "bool")
    c = b.build()
    assert c.depth() == 2
    assert list(c.and_depth) == [1, 0, 2]
    assert list(c.xor_depth) == [0, 1, 0]


def test_inputs_after_gates_are_refused():
    b = CircuitBuilder()
    x = b.input("x", (), 2, "int")
    b.and_(x[0], x[1])
    with pytest.raises(RuntimeError, match="'late'"):
        b.input("late", (), 1)


def test_mux_selects():
    b = CircuitBuilder()
    s = b.input("s", (), 1, "bool")
    x = b.input("x", (), 16, "uint16")
    y = b.input("y", (), 16, "uint16")
    b.output("z", b.mux(s[0], x, y), "uint16")
    c = b.build()
    s_v = np.array([[False], [True]])
    out = evaluate(c, {"s": s_v[:, 0], "x": np.array([1, 2], np.uint16),
                       "y": np.array([3, 4], np.uint16)}, batch=2)
    assert list(out["z"]) == [1, 4]


@pytest.mark.parametrize("dtype,bits", [("float32", 32), ("int32", 32), ("uint8", 8),
                                        ("float64", 64), ("int64", 64), ("uint64", 64)])
def test_value_bits_round_trip(dtype, bits):
    rng = np.random.default_rng(3)
    raw = rng.integers(0, 256, size=(5, 3, bits // 8), dtype=np.uint8)
    vals = raw.view(dtype).reshape(5, 3)
    back = from_bits(to_bits(vals, bits, dtype), dtype)
    assert back.tobytes() == vals.tobytes()


def test_wide_int_round_trip_and_lanes():
    vals = np.array([0, 1, (1 << 127) + 5], dtype=object)
    assert list(from_bits(to_bits(vals, 128, "int"), "int")) == list(vals)
    bits = np.random.default_rng(1).random((7, 130)) < 0.5
    assert np.array_equal(unpack_lanes(pack_lanes(bits), 130), bits)


def test_evaluate_names_the_bad_input():
    b = CircuitBuilder()
    x = b.input("x", (2,), 8, "uint8")
    b.output("y", x, "uint8")
    c = b.build()
    with pytest.raises(ValueError, match="'x'"):
        evaluate(c, {"x": np.zeros(3, np.uint8)})
    with pytest.raises(ValueError, match="missing"):
        evaluate(c, {})


def test_and_gate_limit_stops_a_build_that_crosses_it():
    with and_gate_limit(40):
        b = CircuitBuilder()
        x, y = b.input("x", (), 32, "int"), b.input("y", (), 32, "int")
        b.and_(x, y)  # 32: within the limit
        b.and_(x, ONE)  # folded: no gate, nothing counted
        with pytest.raises(CircuitTooLarge, match="more than 40 AND gates"):
            b.and_(x[:9], y[:9])
        assert b.n_gates == 32  # the batch that crossed the limit was not emitted
    unlimited = CircuitBuilder()  # the limit ends with its block
    x = unlimited.input("x", (), 64, "int")
    unlimited.and_(x, x[::-1])
    assert unlimited.n_gates == 64
