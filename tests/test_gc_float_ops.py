"""Every float32 op, garbled and evaluated, decodes to exactly its cleartext evaluation.

One circuit per op holds ``LANES`` independent instances, so one garbled run checks a whole
batch of values; the oracle is the cleartext evaluator on the same schedule, compared bit
for bit (NaN payloads and zero signs included).
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from snail_common.arith.catalog import OPS
from snail_common.circuit import (
    CircuitBuilder,
    decode_outputs,
    encode_inputs,
    evaluate_bits,
    schedule_circuit,
)
from snail_common.gc import garbled_run

LANES = 64

REQUIRED = {"add", "sub", "mul", "div", "div_depth_opt", "sqrt", "lt", "le", "eq", "min", "max",
            "i2f", "f2i", "mul_const"}

F32_EDGES = np.array([0.0, -0.0, 1.0, -1.0, 1.5, 3.0, 2.0 ** -24, 1 - 2.0 ** -24,
                      np.finfo(np.float32).max, -np.finfo(np.float32).max, 2.0 ** -126,
                      -(2.0 ** -126), np.inf, -np.inf, np.nan], np.float32)
F32_EDGES = np.concatenate([F32_EDGES, np.array([1, 0x807FFFFF], np.uint32).view(np.float32)])
I32_EDGES = np.array([0, 1, -1, 2 ** 31 - 1, -(2 ** 31), 2 ** 24 + 1, -(2 ** 25 + 2), 16777217,
                      123456789, -7], np.int32)


class Op:
    """One op's circuit over LANES lanes, built and scheduled once."""

    def __init__(self, name: str) -> None:
        fn, n_args, in_dtype, out_dtype = OPS[name]
        b = CircuitBuilder()
        args = [b.input(f"x{i}", (LANES,), 32, in_dtype) for i in range(n_args)]
        out = fn(b, *args)
        b.output("r", out[..., None] if out_dtype == "bool" else out, out_dtype)
        self.circuit = b.build()
        self.schedule = schedule_circuit(self.circuit)
        self.n_args, self.dtype = n_args, np.dtype(in_dtype)

    def check(self, *values: np.ndarray, scheme: str = "halfgates") -> np.ndarray:
        """Garble one batch of LANES values per argument; assert the decoded bits equal the
        cleartext bits; return the decoded outputs."""
        named = {f"x{i}": np.asarray(v, self.dtype) for i, v in enumerate(values)}
        bits = encode_inputs(self.circuit, named)[0]
        want = evaluate_bits(self.schedule, bits[None])[0]
        got = garbled_run(self.schedule, bits, scheme)
        assert np.array_equal(got, want), f"{int((got != want).sum())} output bits differ"
        return decode_outputs(self.circuit, got[None])["r"]


@pytest.fixture(scope="module")
def op():
    cache: dict[str, Op] = {}

    def get(name: str) -> Op:
        if name not in cache:
            cache[name] = Op(name)
        return cache[name]
    return get


def test_every_required_op_is_covered():
    assert set(OPS) >= REQUIRED


def lane_values(dtype: np.dtype):
    """LANES values of any bit pattern (NaNs, infinities, subnormals included)."""
    if dtype == np.int32:
        return arrays(np.int32, LANES)
    return st.one_of(
        arrays(np.float32, LANES, elements=st.floats(width=32)),
        arrays(np.uint32, LANES).map(lambda u: u.view(np.float32)),
        arrays(np.float32, LANES, elements=st.sampled_from(F32_EDGES.tolist())))


@pytest.mark.parametrize("name", sorted(OPS))
@settings(max_examples=6, deadline=None)
@given(data=st.data())
def test_random_batch_matches_cleartext(op, name, data):
    o = op(name)
    o.check(*(data.draw(lane_values(o.dtype), label=f"x{i}") for i in range(o.n_args)))


@pytest.mark.parametrize("name", sorted(OPS))
def test_edge_cases_match_cleartext(op, name):
    """All pairs of edge values (binary ops), all edge values (unary ops), LANES at a time."""
    o = op(name)
    edges = I32_EDGES if o.dtype == np.int32 else F32_EDGES
    grids = [g.ravel() for g in np.meshgrid(*[edges] * o.n_args)]
    size = -(-len(grids[0]) // LANES) * LANES
    grids = [np.resize(g, size) for g in grids]  # the last batch wraps around
    for k in range(0, size, LANES):
        o.check(*(g[k : k + LANES] for g in grids))


@pytest.mark.parametrize("name", sorted(OPS))
def test_three_halves_matches_cleartext(op, name):
    """Every op garbled with three-halves: one batch of edge and random values."""
    o = op(name)
    rng = np.random.default_rng(len(name))
    if o.dtype == np.int32:
        pool = np.concatenate([I32_EDGES, rng.integers(-2**31, 2**31, LANES, dtype=np.int32)])
    else:
        pool = np.concatenate([F32_EDGES, rng.standard_normal(LANES).astype(np.float32)])
    o.check(*(rng.choice(pool, LANES) for _ in range(o.n_args)), scheme="threehalves")


def test_decoded_values_are_the_float_results(op):
    """The garbled outputs decode to the float32 results themselves, not just to matching
    bits: a guard against an oracle that agrees with the engine for the wrong reason."""
    x = np.linspace(-3, 5, LANES, dtype=np.float32)
    y = np.linspace(0.5, 7, LANES, dtype=np.float32)
    assert np.array_equal(op("add").check(x, y), x + y)
    assert np.array_equal(op("mul").check(x, y), x * y)
    assert np.array_equal(op("div").check(x, y), x / y)
    assert np.array_equal(op("sqrt").check(y), np.sqrt(y))
    assert np.array_equal(op("lt").check(x, y), x < y)
