"""The vectorized half-gates kernels and the garbler's stream against a scalar reference
written from the definitions (Python integers, one AES call per block)."""

import numpy as np
from cryptography.hazmat.primitives.ciphers import Cipher, algorithms, modes
from hypothesis import given, settings
from hypothesis import strategies as st

from snail_common.circuit import AndStep, CircuitBuilder, schedule_circuit
from snail_common.gc import Garbler, derive_zero_labels, fresh_delta, fresh_seed
from snail_common.gc.halfgates import HalfGates
from snail_common.gc.stream import HEADER, Header

M64 = (1 << 64) - 1


def to_int(label) -> int:
    return int(label[0]) | int(label[1]) << 64


def to_label(v: int) -> np.ndarray:
    return np.array([v & M64, v >> 64], np.uint64)


class Ref:
    """H(x, i) = AES_k(sigma(x) ^ i) ^ sigma(x), sigma(xL || xR) = (xL ^ xR || xL), with
    xL the low word; the tweak sits in the high word."""

    def __init__(self, key: bytes, delta: int) -> None:
        self.enc = Cipher(algorithms.AES(key), modes.ECB()).encryptor()
        self.d = delta

    def h(self, x: int, i: int) -> int:
        lo, hi = x & M64, x >> 64
        s = (lo ^ hi) | lo << 64
        y = int.from_bytes(self.enc.update((s ^ (i << 64)).to_bytes(16, "little")), "little")
        return y ^ s

    def garble(self, a0: int, b0: int, g: int) -> tuple[int, int, int]:
        pa, pb, d = a0 & 1, b0 & 1, self.d
        tg = self.h(a0, 2 * g) ^ self.h(a0 ^ d, 2 * g) ^ (d if pb else 0)
        te = self.h(b0, 2 * g + 1) ^ self.h(b0 ^ d, 2 * g + 1) ^ a0
        c0 = self.h(a0, 2 * g) ^ (tg if pa else 0) ^ self.h(b0, 2 * g + 1) ^ (te ^ a0 if pb else 0)
        return tg, te, c0


@settings(max_examples=25, deadline=None)
@given(n=st.integers(1, 40), g0=st.integers(0, 2**40), seed=st.integers(0, 2**32))
def test_kernels_match_reference(n, g0, seed):
    rng = np.random.default_rng(seed)
    key, delta = rng.bytes(16), fresh_delta()
    labels = rng.integers(0, 2**64, (50, 2), dtype=np.uint64)
    a = rng.integers(0, 50, n).astype(np.int32)
    b = rng.integers(0, 50, n).astype(np.int32)
    ref = Ref(key, to_int(delta))
    kernel = HalfGates(key, 64, delta)
    tables = np.empty((2 * n, 2), np.uint64)
    c0 = np.empty((n, 2), np.uint64)
    kernel.garble(labels, a, b, g0, c0, tables)
    for i in range(n):
        tg, te, c = ref.garble(to_int(labels[a[i]]), to_int(labels[b[i]]), g0 + i)
        assert (to_int(tables[i]), to_int(tables[n + i]), to_int(c0[i])) == (tg, te, c)

    # evaluation on active labels for random bits gives C0 ^ (va & vb) * D; a slot may be
    # both an a and a b operand, so the a-side bits index slots 0..49 and the b-side bits a
    # copy of the labels at slots 50..99
    va, vb = rng.integers(0, 2, 50).astype(bool), rng.integers(0, 2, 50).astype(bool)
    active = labels ^ np.where(va[:, None], delta, 0).astype(np.uint64)
    active_b = labels ^ np.where(vb[:, None], delta, 0).astype(np.uint64)
    both = np.concatenate([active, active_b])
    c = np.empty((n, 2), np.uint64)
    HalfGates(key, 64).evaluate(both, a, b + 50, g0, c, tables)
    # the reference zero-labels for operand b now come from the second half (same values)
    expect = c0 ^ np.where((va[a] & vb[b])[:, None], delta, 0).astype(np.uint64)
    assert np.array_equal(c, expect)


def reference_garble(schedule, zero_inputs, delta, key):
    """Scalar garbler over the schedule: (tables per AND in schedule order, output zero-labels)."""
    ref = Ref(key, to_int(delta))
    slots = {i: to_int(v) for i, v in enumerate(zero_inputs)}
    tables, g = [], 0
    for step in schedule.steps():
        if isinstance(step, AndStep):
            new = []
            for o, a, b in zip(step.out.tolist(), step.a.tolist(), step.b.tolist()):
                tg, te, c0 = ref.garble(slots[a], slots[b], g)
                tables.append((tg, te))
                new.append((o, c0))
                g += 1
        else:
            ends = list(step.starts[1:]) + [len(step.terms)]
            new = []
            for o, s, e in zip(step.out.tolist(), step.starts.tolist(), ends):
                v = 0
                for t in step.terms[s:e].tolist():
                    v ^= slots[t]
                new.append((o, v))
        slots.update(new)
    return tables, [slots[s] for s in schedule.output_slots.tolist()]


def test_garbler_stream_matches_reference_layout():
    """Header, then per AND step blocks of block_gates gates: all TG, then all TE."""
    b = CircuitBuilder()
    x = b.input("x", 16, 1)[:, 0]
    y = b.and_(x[:8], x[8:])  # 8 gates: blocks of 3, 3, 2
    z = b.xor(b.and_(y[:4], y[4:]), x[:4])  # 4 gates after a linear step
    w = b.and_(z[:2], b.not_(z[2:]))
    b.output("o", np.concatenate([w, y[:3]]))
    schedule = schedule_circuit(b.build())
    seed, delta = fresh_seed(), fresh_delta()
    garbler = Garbler(schedule, seed, delta, block_gates=3, frame_bytes=200)
    frames = list(garbler.frames())
    header = Header.unpack(frames[0])
    assert len(frames[0]) == HEADER.size
    assert (header.n_and, header.block_gates) == (schedule.n_and, 3)
    assert all(len(f) % 32 == 0 and len(f) <= 200 for f in frames[1:])
    stream = b"".join(frames[1:])
    assert len(stream) == 32 * schedule.n_and
    words = np.frombuffer(stream, np.uint64).reshape(-1, 2)
    got, pos = [], 0
    for step in schedule.steps():
        if isinstance(step, AndStep):
            for k in range(0, len(step.out), 3):
                m = min(3, len(step.out) - k)
                got += [(to_int(words[pos + i]), to_int(words[pos + m + i])) for i in range(m)]
                pos += 2 * m
    zero_inputs = derive_zero_labels(seed, 2 + schedule.n_inputs)
    tables, outputs = reference_garble(schedule, zero_inputs, delta, header.key)
    assert got == tables
    assert [to_int(v) for v in garbler.output_zero_labels] == outputs
