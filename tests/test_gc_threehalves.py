"""Three-halves kernel: correct for every input pair and every random choice of the garbler,
control bits and ciphertexts that matter break the output when tampered with, unique hash
inputs, and the stream's size per AND gate."""

import numpy as np
import pytest

from snail_common.circuit import CircuitBuilder, evaluate_bits, schedule_circuit
from snail_common.gc import (
    Evaluator,
    Garbler,
    StreamError,
    active_input_labels,
    decode_output_labels,
    fresh_delta,
    fresh_seed,
)
from snail_common.gc import threehalves as th
from snail_common.gc.stream import (
    HEADER,
    SCHEME_THREE_HALVES,
    Header,
    control_words,
    table_words,
)

KEY = bytes(range(16))


def random_labels(rng, n):
    return rng.integers(0, 2**64, (n, 2), dtype=np.uint64)


def garble_block(rng, n, g0, delta, random_key=b"r" * 16):
    labels = random_labels(rng, 2 * n)
    a, b = np.arange(n), np.arange(n, 2 * n)
    zero = np.empty((n, 2), np.uint64)
    tables = np.zeros(table_words(SCHEME_THREE_HALVES, n), np.uint64)
    th.ThreeHalves(KEY, 512, delta, random_key).garble(labels, a, b, g0, zero, tables)
    return labels, a, b, zero, tables


def evaluate_block(labels, a, b, g0, tables, delta, x, y):
    """Active output labels for inputs x (on a) and y (on b), per gate; the output is
    written over the operand rows a, which the kernel must read first."""
    n = len(a)
    active = labels.copy()
    active[a] ^= delta * x[:, None].astype(np.uint64)
    active[b] ^= delta * y[:, None].astype(np.uint64)
    th.ThreeHalves(KEY, 512).evaluate(active, a, b, g0, active[:n], tables)
    return active[:n]


@pytest.mark.parametrize(("n", "g0"), [(1, 0), (7, 5), (300, 123_456_789), (512, 2**40)])
def test_every_input_pair_gives_the_right_label(n, g0):
    rng = np.random.default_rng(n)
    delta = fresh_delta()
    labels, a, b, zero, tables = garble_block(rng, n, g0, delta)
    for x in (0, 1):
        for y in (0, 1):
            ones = np.full(n, x, bool), np.full(n, y, bool)
            got = evaluate_block(labels, a, b, g0, tables, delta, *ones)
            want = zero ^ (delta * np.uint64(x & y))
            assert np.array_equal(got, want), (x, y)


@pytest.mark.parametrize("r", [(0, 0), (0, 1), (1, 0), (1, 1)])
def test_every_random_choice_of_the_garbler_is_correct(monkeypatch, r):
    """Whatever the garbler's two random bits, every colour pair and every pair of truth
    values decodes right (random labels cover all four (alpha, beta))."""
    monkeypatch.setattr(th._RandomBits, "bits",
                        lambda self, g0, n: np.array(r, np.uint64)[:, None].repeat(n, 1))
    rng = np.random.default_rng(sum(r))
    n, delta = 200, fresh_delta()
    labels, a, b, zero, tables = garble_block(rng, n, 0, delta)
    lsb = labels[:, 0] & np.uint64(1)
    assert len({(int(p), int(q)) for p, q in zip(lsb[a], lsb[b])}) == 4
    for x in (0, 1):
        for y in (0, 1):
            got = evaluate_block(labels, a, b, 0, tables, delta, np.full(n, x), np.full(n, y))
            assert np.array_equal(got, zero ^ (delta * np.uint64(x & y)))


def test_random_bits_are_keyed_reproducible_and_balanced():
    bits = th._RandomBits(b"k" * 16, 4096)
    first = bits.bits(70, 4000).copy()
    assert np.array_equal(bits.bits(70, 4000), first)
    assert np.array_equal(bits.bits(1000, 5), first[:, 930:935])  # indexed by gate number
    assert not np.array_equal(th._RandomBits(b"K" * 16, 4096).bits(70, 4000), first)
    assert set(np.unique(first)) == {0, 1}
    assert abs(first.mean() - 0.5) < 0.03
    assert th.control_key(b"s" * 16) != th.control_key(b"t" * 16)


def test_the_garbler_s_random_bits_reach_the_stream():
    """The same labels garbled under two random keys give different control bits z0, z1
    (r0, r1 enter them one to one) and the same z2..z4 (which do not depend on them)."""
    n, delta = 256, fresh_delta()
    one = garble_block(np.random.default_rng(3), n, 0, delta, b"a" * 16)
    two = garble_block(np.random.default_rng(3), n, 0, delta, b"b" * 16)
    z1, z2 = (np.unpackbits(t[3 * n :].view(np.uint8), bitorder="little")[: 5 * n]
              .reshape(5, n) for t in (one[4], two[4]))
    assert (z1[:2] != z2[:2]).mean() > 0.3
    assert np.array_equal(z1[2:], z2[2:])


def test_a_flipped_table_bit_breaks_the_output_exactly_when_used():
    """G0 is used iff the colour i of a is 1, G1 iff j is 1, G2 iff i != j; control bits
    z0, z1 always, z2 iff i, z3 iff j, z4 iff i != j. A used, flipped bit shifts the output
    label off both valid values; an unused one changes nothing."""
    rng = np.random.default_rng(11)
    n, delta = 64, fresh_delta()
    labels, a, b, zero, tables = garble_block(rng, n, 9, delta)
    x, y = rng.integers(0, 2, n), rng.integers(0, 2, n)
    good = evaluate_block(labels, a, b, 9, tables, delta, x, y)
    assert np.array_equal(good, zero ^ (delta * (x & y).astype(np.uint64)[:, None]))
    i = ((labels[a, 0] & np.uint64(1)) ^ x.astype(np.uint64)).astype(bool)
    j = ((labels[b, 0] & np.uint64(1)) ^ y.astype(np.uint64)).astype(bool)
    uses = {"G0": i, "G1": j, "G2": i != j, "z0": np.ones(n, bool), "z1": np.ones(n, bool),
            "z2": i, "z3": j, "z4": i != j}
    broken = 0
    for gate in range(0, n, 3):
        for part, used in uses.items():
            bad = tables.copy()
            k = int(part[1])
            if part[0] == "G":
                bad[k * n + gate] ^= np.uint64(1) << np.uint64(rng.integers(0, 64))
            else:
                bit = k * n + gate
                bad.view(np.uint8)[3 * n * 8 + bit // 8] ^= np.uint8(1 << (bit % 8))
            got = evaluate_block(labels, a, b, 9, bad, delta, x, y)
            others = np.arange(n) != gate
            assert np.array_equal(got[others], good[others])
            valid = {tuple(zero[gate]), tuple(zero[gate] ^ delta)}
            assert (tuple(got[gate]) not in valid) == bool(used[gate]), (gate, part)
            broken += bool(used[gate])
    assert broken > 50


def chain(width: int, depth: int):
    """``width`` independent chains of ``depth`` pairs of AND gates."""
    b = CircuitBuilder()
    x = b.input("x", (width, 2), 1)[..., 0]
    acc = [x[:, 0], x[:, 1]]
    for _ in range(depth):
        acc = [b.and_(acc[0], acc[1]), b.and_(acc[0], b.not_(acc[1]))]
    b.output("y", np.stack(acc, 1))
    return schedule_circuit(b.build())


def repeated(copies: int, depth: int):
    """The same AND gate on the same wires ``copies`` times per level, so equal labels
    reach the hash at many gate numbers: only the tweaks keep the AES inputs apart."""
    b = CircuitBuilder()
    x = b.input("x", 2, 1)[:, 0]
    acc, outs = x, []
    for _ in range(depth):
        level = b.and_(np.repeat(acc[0], copies), np.repeat(acc[1], copies))
        outs.append(level)
        acc = level[:2]
    b.output("y", np.concatenate(outs)[:, None])
    return schedule_circuit(b.build())


@pytest.mark.parametrize("block", [3, 32])
def test_every_hash_input_of_a_run_is_unique(monkeypatch, block):
    seen: dict[int, list[bytes]] = {}

    class Recording(th.AesBatch):
        def encrypt_into(self, src, dst):
            seen.setdefault(id(self), []).append(bytes(src))
            super().encrypt_into(src, dst)

    monkeypatch.setattr(th, "AesBatch", Recording)
    schedule = repeated(40, 3)
    bits = np.zeros(schedule.n_inputs, bool)
    seed, delta = fresh_seed(), fresh_delta()
    # the numpy engine's AES calls are recorded (the native kernel hashes the same
    # blocks: tests/test_gc_native.py holds it to the numpy engine's stream)
    garbler = Garbler(schedule, seed, delta, block_gates=block, scheme="threehalves",
                      engine="numpy")
    ev = Evaluator(schedule, active_input_labels(seed, delta, bits), engine="numpy")
    for frame in garbler.frames():
        ev.feed(frame)
    out = decode_output_labels(delta, garbler.output_zero_labels, ev.output_labels())
    assert np.array_equal(out, evaluate_bits(schedule, bits[None])[0])
    per_aes = {k: b"".join(v) for k, v in seen.items()}
    hashed = [blob for blob in per_aes.values() if len(blob) >= 3 * 16 * schedule.n_and]
    assert sorted(len(blob) // 16 for blob in hashed) == [3 * schedule.n_and,
                                                          6 * schedule.n_and]
    for blob in hashed:
        blocks = np.frombuffer(blob, "V16")
        assert len(np.unique(blocks)) == len(blocks)


def test_stream_size_and_ratio_to_half_gates():
    schedule = chain(4096, 2)
    n = schedule.n_and
    sizes = {}
    for scheme in ("halfgates", "threehalves"):
        g = Garbler(schedule, fresh_seed(), fresh_delta(), block_gates=4096, scheme=scheme)
        sizes[scheme] = sum(len(f) for f in g.frames()) - HEADER.size
    assert sizes["halfgates"] == 32 * n
    assert sizes["threehalves"] == 24 * n + 8 * control_words(4096) * (n // 4096)
    assert sizes["threehalves"] / sizes["halfgates"] == pytest.approx(197 / 256)


def test_schemes_are_checked():
    schedule = chain(2, 1)
    with pytest.raises(ValueError, match="unknown garbling scheme"):
        Garbler(schedule, fresh_seed(), fresh_delta(), scheme="quarter")
    header = Header(1, 2, 3, 4, KEY, SCHEME_THREE_HALVES)
    assert Header.unpack(header.pack()) == header
    with pytest.raises(StreamError, match="unknown garbling scheme 7"):
        Header.unpack(header._replace(scheme=7).pack())
    with pytest.raises(ValueError, match="random bits"):
        th.ThreeHalves(KEY, 4, fresh_delta())


def test_garbling_is_reproducible_from_the_run_secrets():
    """Same seed, offset and key: the same stream (garble-ahead and lanes rely on it);
    another seed: other control bits and labels."""
    schedule = chain(100, 3)
    seed, delta = fresh_seed(), fresh_delta()
    one = b"".join(Garbler(schedule, seed, delta, KEY, scheme="threehalves").frames())
    two = b"".join(Garbler(schedule, seed, delta, KEY, scheme="threehalves").frames())
    other = b"".join(Garbler(schedule, fresh_seed(), delta, KEY, scheme="threehalves").frames())
    assert one == two and one != other and len(one) == len(other)
