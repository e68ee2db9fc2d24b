"""Integer circuits against numpy / Python integers on whole batches of inputs."""

import itertools

import numpy as np
import pytest
from arith_harness import Compiled
from hypothesis import given, settings
from hypothesis import strategies as st

from snail_common.arith import integer as I
from snail_common.arith import multiply as M
from snail_common.arith import prefix as P
from snail_common.arith import shift as S
from snail_common.arith.words import bit, cat
from snail_common.circuit import ONE

N = 16
MASK = (1 << N) - 1
RNG = np.random.default_rng(12345)
U = "uint64"


def _edge_and_random(n_bits: int, count: int = 3000) -> np.ndarray:
    edges = [0, 1, 2, (1 << n_bits) - 1, (1 << n_bits) - 2, 1 << (n_bits - 1),
             (1 << (n_bits - 1)) - 1]
    rand = RNG.integers(0, 1 << n_bits, count, dtype=np.uint64)
    shifts = RNG.integers(0, n_bits, count).astype(np.uint64)
    return np.concatenate([np.array(edges, np.uint64), rand >> shifts])


def _pairs(n_bits: int):
    a = _edge_and_random(n_bits)
    b = _edge_and_random(n_bits)
    k = len(a)
    return np.concatenate([a, a, np.repeat(a[:7], 7)]), np.concatenate(
        [b, a ^ (RNG.integers(0, 2, k, dtype=np.uint64) << RNG.integers(0, n_bits, k)
                 .astype(np.uint64)), np.tile(a[:7], 7)])


def _signed(v: np.ndarray, n_bits: int = N) -> np.ndarray:
    v = v.astype(np.int64)
    return np.where(v >> (n_bits - 1) & 1, v - (1 << n_bits), v)


TWO = {"x": (N, U), "y": (N, U)}


def _cat2(pair):
    """(word, wire) or (wire, word) -> one word."""
    return cat(*(p if np.ndim(p) else bit(p) for p in pair))
CIRCUITS = {
    "add": (lambda b, x, y: I.add(b, x, y), TWO, U),
    "add_carry": (lambda b, x, y: _cat2(I.add_carry(b, x, y)), TWO, U),
    "add_cin": (lambda b, x, y: I.add(b, x[..., :-1], y[..., :-1], x[..., -1]), TWO, U),
    "add_fast": (lambda b, x, y: P.add_fast(b, x, y, y[..., 0]), TWO, U),
    "increment_fast": (lambda b, x, y: _cat2(P.increment_fast(b, x, y[..., 0])), TWO, U),
    "prefix_and": (lambda b, x, y: P.prefix_and(b, x), TWO, U),
    "carry_out_tree": (lambda b, x, y: np.stack([P.carry_out_tree(b, x, y),
                                                 P.carry_out_tree(b, x, y, ONE),
                                                 P.carry_out_tree(b, x[..., :11], y[..., 3:14],
                                                                  y[..., 0])], -1), TWO, U),
    "sub_borrow": (lambda b, x, y: _cat2(I.sub_borrow(b, x, y)), TWO, U),
    "add_sub": (lambda b, x, y: I.add_sub(b, x, y, y[..., 3]), TWO, U),
    "negate": (lambda b, x, y: I.negate(b, x), TWO, U),
    "cond_negate": (lambda b, x, y: I.cond_negate(b, x, y[..., 0]), TWO, U),
    "cmp": (lambda b, x, y: np.stack([I.lt(b, x, y), I.le(b, x, y), I.eq(b, x, y),
                                      I.lt(b, x, y, signed=True), I.le(b, x, y, signed=True),
                                      I.ge(b, x, y), I.gt(b, x, y, signed=True)], -1),
            TWO, U),
    "select": (lambda b, x, y: I.select(b, y[..., 5], x, y), TWO, U),
    "shl": (lambda b, x, y: S.shl(b, x, y[..., :5]), TWO, U),
    "shr": (lambda b, x, y: S.shr(b, x, y[..., :5]), TWO, U),
    "sar": (lambda b, x, y: S.shr(b, x, y[..., :4], arithmetic=True), TWO, U),
    "shr_sticky": (lambda b, x, y: _cat2(S.shr_sticky(b, x, y[..., :5])[::-1]), TWO, U),
    "lzc": (lambda b, x, y: S.lzc(b, x), TWO, U),
    "normalize": (lambda b, x, y: cat(*S.normalize(b, x)), TWO, U),
    "const_shifts": (lambda b, x, y: cat(S.shl_const(x, 3), S.shr_const(x, 5),
                                         S.shr_const(x, 2, arithmetic=True)), TWO, U),
    "mul_schoolbook": (lambda b, x, y: M.mul(b, x, y, "schoolbook"), TWO, U),
    "mul_karatsuba": (lambda b, x, y: M.mul(b, x, y, "karatsuba"), TWO, U),
    "mul_radix4": (lambda b, x, y: M.mul(b, x, y, "radix4"), TWO, U),
    "mul_odd_widths": (lambda b, x, y: M.mul(b, x[..., :13], y[..., :10]), TWO, U),
}


@pytest.fixture(scope="module")
def circ():
    cache = {}

    def get(name):
        if name not in cache:
            fn, ins, out = CIRCUITS[name]
            cache[name] = Compiled(fn, ins, out)
        return cache[name]
    return get


def _ints(v) -> list[int]:
    return [int(t) for t in v]


def _expect(name: str, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    xs, ys = x.astype(object), y.astype(object)
    sx, sy = _signed(x).astype(object), _signed(y).astype(object)
    if name == "add":
        return (xs + ys) & MASK
    if name == "add_carry":
        return (xs + ys) & ((MASK << 1) | 1)
    if name == "add_cin":
        return ((xs & (MASK >> 1)) + (ys & (MASK >> 1)) + (xs >> (N - 1))) & (MASK >> 1)
    if name == "add_fast":
        return (xs + ys + (ys & 1)) & MASK
    if name == "increment_fast":
        return xs + (ys & 1)
    if name == "prefix_and":
        return sum(((xs & ((2 << i) - 1)) == (2 << i) - 1).astype(object) << i for i in range(N))
    if name == "carry_out_tree":
        c11 = ((xs & 0x7FF) + ((ys >> 3) & 0x7FF) + (ys & 1)) >> 11
        return ((xs + ys) >> N) | (((xs + ys + 1) >> N) << 1) | (c11 << 2)
    if name == "sub_borrow":
        return ((xs - ys) & MASK) | ((xs < ys).astype(object) << N)
    if name == "add_sub":
        return np.where((ys >> 3) & 1, xs - ys, xs + ys) & MASK
    if name == "negate":
        return (-xs) & MASK
    if name == "cond_negate":
        return np.where(ys & 1, -xs, xs) & MASK
    if name == "cmp":
        flags = [xs < ys, xs <= ys, xs == ys, sx < sy, sx <= sy, xs >= ys, sx > sy]
        return sum(f.astype(object) << i for i, f in enumerate(flags))
    if name == "select":
        return np.where((ys >> 5) & 1, ys, xs)
    if name == "shl":
        return (xs << (ys & 31)) & MASK
    if name == "shr":
        return xs >> (ys & 31)
    if name == "sar":
        return (sx >> (ys & 15)) & MASK
    if name == "shr_sticky":
        k = ys & 31
        sticky = np.array([int(a) & ((1 << int(s)) - 1) != 0 for a, s in zip(xs, k)], object)
        return sticky | ((xs >> k) << 1)
    if name == "lzc":
        return np.array([N - int(a).bit_length() for a in xs], object)
    if name == "normalize":
        lz = np.array([min(N - int(a).bit_length(), 15) if a else 15 for a in xs], object)
        return ((xs << lz) & MASK) | (lz << N)
    if name == "const_shifts":
        return ((xs << 3) & MASK) | ((xs >> 5) << N) | (((sx >> 2) & MASK) << (2 * N))
    if name.startswith("mul_") and name != "mul_odd_widths":
        return xs * ys
    if name == "mul_odd_widths":
        return (xs & 0x1FFF) * (ys & 0x3FF)
    raise KeyError(name)


@pytest.mark.parametrize("name", list(CIRCUITS))
def test_integer_op_on_a_batch(circ, name):
    x, y = _pairs(N)
    got = circ(name)(x, y).astype(object)
    want = _expect(name, x, y)
    bad = np.flatnonzero(got != want)
    assert bad.size == 0, (name, [(int(x[i]), int(y[i]), got[i], want[i]) for i in bad[:5]])


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.integers(0, MASK), st.integers(0, MASK)), min_size=1,
                max_size=40), st.sampled_from(list(CIRCUITS)))
def test_integer_ops_hypothesis(circ, pairs, name):
    x = np.array([p[0] for p in pairs], np.uint64)
    y = np.array([p[1] for p in pairs], np.uint64)
    got = circ(name)(x, y).astype(object)
    assert list(got) == list(_expect(name, x, y))


@pytest.mark.parametrize("c", [0, 1, 2, 3, 5, 7, 11, 12345, 0xB504F3, (1 << 23) + 1, 1 << 20,
                               0xAAAAAA, 0xFFFFFF])
def test_mul_const_matches_python(c):
    circuit = Compiled(lambda b, x: M.mul_const(b, x, c), {"x": (24, U)}, "int")
    x = _edge_and_random(24, 500)
    got = circuit(x)
    assert [int(v) for v in got] == [int(v) * c for v in x]


def test_mul_const_is_cheaper_than_mul():
    general = Compiled(lambda b, x, y: M.mul(b, x, y), {"x": (24, U), "y": (24, U)}, U).ands
    for c in (3, 0xB504F3, 0xFFFFFF, 0xAAAAAB):
        assert Compiled(lambda b, x, c=c: M.mul_const(b, x, c), {"x": (24, U)}, U).ands < general


def test_costs_follow_the_cost_model():
    cost = lambda fn: Compiled(fn, TWO, U).ands  # noqa: E731
    assert cost(lambda b, x, y: I.add(b, x, y)) == N - 1
    assert cost(lambda b, x, y: _cat2(I.add_carry(b, x, y))) == N
    assert cost(lambda b, x, y: bit(I.lt(b, x, y))) == N
    assert cost(lambda b, x, y: bit(I.eq(b, x, y))) == N - 1
    assert cost(lambda b, x, y: I.select(b, y[..., 0], x, y)) == N
    radix4 = cost(lambda b, x, y: M.mul(b, x, y, "radix4"))
    school = cost(lambda b, x, y: M.mul(b, x, y, "schoolbook"))
    assert radix4 < school


def test_prefix_adder_is_shallower():
    ripple = Compiled(lambda b, x, y: I.add(b, x, y), TWO, U).circuit.depth()
    fast = Compiled(lambda b, x, y: P.add_fast(b, x, y), TWO, U).circuit.depth()
    assert ripple == N - 1 and fast <= 5
    tree = Compiled(lambda b, x, y: bit(P.carry_out_tree(b, x, y, ONE)), TWO, U)
    assert tree.circuit.depth() <= 6 and tree.ands <= 3 * N     # log depth, linear size
    pand = Compiled(lambda b, x, y: P.prefix_and(b, x), TWO, U)
    assert pand.circuit.depth() == 4 and pand.ands == N // 2 * 4


def test_csd_digits_reconstruct():
    for c in list(range(200)) + [0xB504F3, 0xFFFFFF]:
        digits = M.csd_digits(c)
        assert sum(d << p for p, d in digits) == c
        pos = [p for p, _ in digits]
        assert all(b - a >= 2 for a, b in itertools.pairwise(pos))
