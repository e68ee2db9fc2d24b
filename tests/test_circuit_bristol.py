"""Every shared Bristol file, in the clear, against a direct computation; export round trip."""


import numpy as np
import pytest
from shared_paths import BRISTOL

from snail_common.circuit import evaluate, schedule_circuit
from snail_common.circuit.bristol import BristolError, dump_bristol, load_bristol, parse_bristol

LANES = 300
rng = np.random.default_rng(2024)
U = rng.integers(0, 2**64, LANES, dtype=np.uint64)
V = rng.integers(0, 2**64, LANES, dtype=np.uint64)


def _doubles(n):
    """Doubles over a wide exponent range, with some exact ties and zeros mixed in."""
    x = rng.normal(size=n) * np.exp2(rng.integers(-60, 60, n))
    x[:5] = [0.0, -0.0, 1.0, -2.5, 3.0]
    return x


def _i64(u):
    return u.view(np.int64)


def _signed_div(x, y):
    x, y = _i64(x), _i64(y)
    y = np.where(y == 0, 1, y)
    q = np.abs(x) // np.abs(y)  # C semantics: truncate toward zero
    return np.where((x < 0) ^ (y < 0), -q, q).view(np.uint64), (x, y)


def _cases():
    with np.errstate(over="ignore"):
        X, Y = _doubles(LANES), _doubles(LANES)
        ints = rng.integers(-(2**62), 2**62, LANES)
        ints[:3] = [0, -1, 1 << 53]
        yield "adder64", (U, V), [U + V]
        yield "sub64", (U, V), [U - V]
        yield "neg64", (U,), [(-_i64(U)).view(np.uint64)]
        yield "mult64", (U, V), [U * V]
        lo = U * V
        hi = np.array([(int(a) * int(b)) >> 64 for a, b in zip(U, V)], np.uint64)
        yield "mult2_64", (U, V), [hi, lo]  # this file emits the high word first
        Vn = np.where(V == 0, 1, V)
        yield "udivide64", (U, Vn), [U // Vn]
        q, (xs, ys) = _signed_div(U, V)
        yield "divide64", (xs.view(np.uint64), ys.view(np.uint64)), [q]
        Z = U.copy()
        Z[::3] = 0
        yield "zero_equal", (Z,), [(Z == 0).astype(np.uint64)]
        yield "FP-add", (X.view(np.uint64), Y.view(np.uint64)), [(X + Y).view(np.uint64)]
        yield "FP-mul", (X.view(np.uint64), Y.view(np.uint64)), [(X * Y).view(np.uint64)]
        Ye = Y.copy()
        Ye[::4] = X[::4]
        yield "FP-eq", (X.view(np.uint64), Ye.view(np.uint64)), [(Ye == X).astype(np.uint64)]
        yield "FP-lt", (X.view(np.uint64), Y.view(np.uint64)), [(X < Y).astype(np.uint64)]
        F = rng.normal(size=LANES) * 1e6
        # this file rounds to nearest (ties are measure-zero for these inputs)
        yield "FP-f2i", (F.view(np.uint64),), [np.rint(F).astype(np.int64).view(np.uint64)]
        yield "FP-i2f", (ints.view(np.uint64),), [ints.astype(np.float64).view(np.uint64)]
        yield "FP-floor", (F.view(np.uint64),), [np.floor(F).view(np.uint64)]
        yield "FP-ceil", (F.view(np.uint64),), [np.ceil(F).view(np.uint64)]


CASES = {name: (ins, outs) for name, ins, outs in _cases()}


def test_every_shared_file_is_covered():
    assert {p.stem for p in BRISTOL.glob("*.txt") if p.stem.upper() != p.stem} >= set(CASES)
    assert set(CASES) >= {p.stem for p in BRISTOL.glob("*.txt")} - {"LICENSE-SCALE-MAMBA"}


@pytest.mark.parametrize("name", sorted(CASES))
def test_bristol_file_in_the_clear(name):
    circuit = load_bristol(BRISTOL / f"{name}.txt")
    ins, outs = CASES[name]
    values = {f"in{i}": v for i, v in enumerate(ins)}
    got = evaluate(circuit, values, batch=LANES)
    for j, want in enumerate(outs):
        g = got[f"out{j}"]
        if name in ("FP-add", "FP-mul", "FP-i2f", "FP-floor", "FP-ceil"):
            # these circuits canonicalize -0.0 results; compare as doubles
            assert np.array_equal(g.view(np.float64), want.view(np.float64)), name
        elif circuit.output_groups[j].bits == 1 or name in ("FP-eq", "FP-lt"):
            assert np.array_equal(g & 1, want), name
        else:
            assert np.array_equal(g, want), name


@pytest.mark.parametrize("name", sorted(CASES))
def test_export_import_round_trip(name):
    circuit = load_bristol(BRISTOL / f"{name}.txt")
    again = parse_bristol(dump_bristol(circuit))
    assert again.counts() == circuit.counts()
    assert again.depth() == circuit.depth()
    ins, _ = CASES[name]
    values = {f"in{i}": v for i, v in enumerate(ins)}
    a = evaluate(circuit, values, batch=LANES)
    b = evaluate(again, values, schedule_circuit(again), batch=LANES)
    assert all(np.array_equal(a[k], b[k]) for k in a)


def test_export_handles_outputs_that_are_inputs_constants_or_repeats():
    from snail_common.circuit import CircuitBuilder

    b = CircuitBuilder()
    x = b.input("x", (), 3, "int")
    g = b.and_(x[0], x[1])
    b.output("y", np.array([x[2], 1, g, g, b.not_(x[0])]), "int")
    c = b.build()
    again = parse_bristol(dump_bristol(c))
    bits = np.array([[0, 1, 1], [1, 1, 0], [1, 0, 1]], bool)
    from snail_common.circuit import evaluate_bits

    assert np.array_equal(evaluate_bits(schedule_circuit(c), bits),
                          evaluate_bits(schedule_circuit(again), bits))


@pytest.mark.parametrize("text,match", [
    ("1 3\n2 1 1\n1 1\n\n2 1 0 1 2 NAND\n", "unsupported gate"),
    ("2 3\n2 1 1\n1 1\n\n2 1 0 1 2 AND\n", "header says 2 gates"),
    ("1 4\n2 1 1\n1 1\n\n2 1 0 2 3 AND\n", "before it is driven"),
    ("x", "bad header"),
])
def test_malformed_files_are_rejected_with_a_reason(text, match):
    with pytest.raises(BristolError, match=match):
        parse_bristol(text)


def test_shared_folder_is_present():
    """Fail loudly, rather than skip, when the shared circuits are not where CI puts them."""
    assert BRISTOL.is_dir(), f"{BRISTOL} missing: set SNAIL_SHARED to the shared folder"
