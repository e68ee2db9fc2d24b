"""Narrow float formats (fewer fraction bits in a float32 word): the circuits bit for bit
against the mirror, and the mirror against exact rational arithmetic."""

from fractions import Fraction

import numpy as np
import pytest
from arith_harness import Compiled
from hypothesis import given, settings
from hypothesis import strategies as st
from test_arith_float import assert_same, cancelling, finite, near, with_exponent_sum

from snail_common.arith import fadd, fconvert, fmul
from snail_common.arith import mirror as MR

F = "float32"
FRACS = (13, 10, 4)
OPS = {
    "add": (fadd.fadd, MR.add),
    "sub": (fadd.fsub, MR.sub),
    "add_depth_opt": (lambda b, x, y, frac: fadd.fadd(b, x, y, True, frac), MR.add),
    "mul": (lambda b, x, y, frac: fmul.fmul(b, x, y, frac), MR.mul),
}


@pytest.fixture(scope="module")
def circ():
    cache = {}

    def get(name: str, frac: int) -> Compiled:
        if (name, frac) not in cache:
            if name == "round":
                cache[name, frac] = Compiled(lambda b, x: fconvert.fround(b, x, frac),
                                             {"x": (32, F)}, F)
            else:
                fn = OPS[name][0]
                cache[name, frac] = Compiled(lambda b, x, y: fn(b, x, y, frac=frac),
                                             {"x": (32, F), "y": (32, F)}, F)
        return cache[name, frac]
    return get


def run(circ, name: str, frac: int, x, y=None) -> np.ndarray:
    x = np.asarray(x, np.float32)
    if name == "round":
        got = circ(name, frac)(x)
        assert_same(got, MR.fround(x, frac), x)
        return got
    y = np.asarray(y, np.float32)
    got = circ(name, frac)(x, y)
    assert_same(got, OPS[name][1](x, y, frac), x, y)
    return got


def exact_round(value: Fraction, frac: int) -> float:
    """The narrow-format contract from first principles: nearest even at ``frac`` bits,
    unbounded exponent; below 2^-126 a signed zero, from 2^128 an infinity."""
    if value == 0:
        return 0.0
    mag = abs(value)
    e = mag.numerator.bit_length() - mag.denominator.bit_length()
    if Fraction(2) ** e > mag:
        e -= 1
    scaled = mag / Fraction(2) ** (e - frac)          # in [2^frac, 2^(frac+1))
    q = scaled.numerator // scaled.denominator
    rest = scaled - q
    if rest > Fraction(1, 2) or (rest == Fraction(1, 2) and q % 2):
        q += 1
    r = Fraction(q) * Fraction(2) ** (e - frac)
    sign = -1.0 if value < 0 else 1.0
    if r < Fraction(2) ** -126:
        return sign * 0.0
    if r >= Fraction(2) ** 128:
        return sign * np.inf
    return sign * float(r)


def truncated(x: np.float32, frac: int) -> Fraction:
    return Fraction(float(MR.truncate(np.float32(x), frac)))


normal32 = st.floats(width=32, allow_nan=False, allow_infinity=False).filter(
    lambda v: v == 0 or abs(v) >= 2.0 ** -126)


@settings(max_examples=200, deadline=None)
@given(normal32, normal32, st.sampled_from(FRACS + (1, 22)),
       st.sampled_from(["add", "sub", "mul"]))
def test_mirror_is_correctly_rounded(x, y, frac, op):
    """The mirror (float64 then one rounding) equals exact rational arithmetic."""
    a, b = truncated(x, frac), truncated(y, frac)
    exact = {"add": a + b, "sub": a - b, "mul": a * b}[op]
    want = exact_round(exact, frac)
    got = float(getattr(MR, op)(np.float32(x), np.float32(y), frac))
    # an exact zero's sign follows IEEE rules that Fraction cannot see
    assert got == want and (exact == 0 or np.signbit(got) == np.signbit(want)), (x, y, got)


@settings(max_examples=100, deadline=None)
@given(normal32, st.sampled_from(FRACS))
def test_mirror_round_is_correctly_rounded(x, frac):
    assert float(MR.fround(np.float32(x), frac)) == exact_round(Fraction(float(x)), frac)


def _batch(name: str, n: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    x = finite(n)
    y = np.concatenate([finite(n // 3), near(x[n // 3 : 2 * n // 3], 3),
                        near(x[2 * n // 3 :], 20)])
    if name == "mul":  # products near overflow and near 2^-126
        k = n // 4
        y[:k] = with_exponent_sum(x[:k], 254 + 127, 2)
        y[k : 2 * k] = with_exponent_sum(x[k : 2 * k], 1 + 127, 2)
    else:
        y[: n // 2] = cancelling(x[: n // 2])
    return x, y


@pytest.mark.parametrize("frac", FRACS)
@pytest.mark.parametrize("name", list(OPS))
def test_narrow_op_random_batch(circ, name, frac):
    x, y = _batch(name)
    run(circ, name, frac, x, y)
    run(circ, name, frac, y, x)


@pytest.mark.parametrize("frac", FRACS)
def test_round_random_batch(circ, frac):
    x = np.concatenate([finite(3000), MR.from_bits(finite(300).view(np.uint32) & 0x807FFFFF)])
    run(circ, "round", frac, x)


@settings(max_examples=20, deadline=None)
@given(st.lists(st.tuples(normal32, normal32), min_size=1, max_size=64),
       st.sampled_from(["add", "mul"]), st.sampled_from(FRACS))
def test_narrow_ops_hypothesis(circ, pairs, name, frac):
    run(circ, name, frac, [p[0] for p in pairs], [p[1] for p in pairs])


def test_narrow_edge_cases(circ):
    """Ties at the narrow LSB, carries into the exponent, overflow, underflow and the low
    input bits a narrow op must ignore (frac = 4: significands of 5 bits)."""
    one = np.float32(1)
    lsb = np.float32(2.0 ** -4)
    maxn = np.float32((2 - 2.0 ** -4) * 2.0 ** 127)   # largest 4-bit-fraction value
    x = np.float32([1, 1 + 1 / 16, 2 - 1 / 16, 3.5, maxn, 2.0 ** -126 * 1.5, 1 + 2.0 ** -10])
    y = np.float32([1 / 32, 1 / 32, 1 / 32, -3.5, maxn, -(2.0 ** -126), 2.0 ** -10])
    got = run(circ, "add", 4, x, y)
    assert got[0] == one                       # tie, even LSB: stays
    assert got[1] == one + 2 * lsb             # tie, odd LSB: rounds up
    assert got[2] == 2                         # carry into the exponent
    assert MR.bits(got[3]) == 0                # exact cancellation: +0
    assert np.isposinf(got[4])                 # overflow
    assert MR.bits(got[5]) == 0                # 2^-127: flushed
    assert got[6] == one                       # the low input bits are not read
    prods = run(circ, "mul", 4, np.float32([maxn, 1.5 * 2.0 ** -63, 1.5, 1.5 * 2.0 ** -64]),
                np.float32([2, 1.3125 * 2.0 ** -64, -(1 + 1 / 16), 1.25 * 2.0 ** -64]))
    assert np.isposinf(prods[0])
    assert prods[1] == np.float32(2.0 ** -126)  # 1.96875 * 2^-127 rounds up to 2^-126
    assert MR.bits(prods[3]) == 0               # 1.875 * 2^-128: flushed
    assert prods[2] == -(1.5 + 2 * lsb)         # 1.59375 -> tie -> even: 1.625
    rounded = run(circ, "round", 4, np.float32([1 + 1 / 32, 1 + 3 / 32,
                                                np.finfo(np.float32).max, -(2 - 1 / 64),
                                                2.0 ** -130]))
    assert list(rounded[:2]) == [1, 1 + 1 / 8]
    assert np.isposinf(rounded[2]) and rounded[3] == -2 and MR.bits(rounded[4]) == 0


def test_narrow_formats_are_cheaper():
    from snail_common.circuit import CircuitBuilder

    def ands(fn) -> int:
        b = CircuitBuilder()
        x = b.input("x", (), bits=32, dtype=F)
        y = b.input("y", (), bits=32, dtype=F)
        b.output("r", fn(b, x, y), dtype=F)
        return b.build().counts()["and"]

    assert ands(lambda b, x, y: fmul.fmul(b, x, y, frac=13)) < 0.5 * ands(fmul.fmul)
    assert ands(lambda b, x, y: fadd.fadd(b, x, y, frac=13)) < 0.7 * ands(fadd.fadd)
    assert ands(lambda b, x, y: fadd.fadd(b, x, y)) == 528           # float32 unchanged
    with pytest.raises(ValueError, match="frac"):
        fmul.fmul(CircuitBuilder(), np.zeros(32, np.int32), np.zeros(32, np.int32), frac=0)
