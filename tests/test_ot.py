"""Oblivious transfer (snail_common/ot): base OTs and IKNP extension give the receiver
exactly its chosen messages; what each side sees depends on the other side's secret only
in the ways the protocol's argument says; malformed messages are named errors."""

from __future__ import annotations

import contextlib
import random

import msgpack
import nacl.bindings as sodium
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shared_paths import BRISTOL

from snail_common.circuit import evaluate_bits, schedule_circuit
from snail_common.circuit.bristol import load_bristol
from snail_common.gc import (
    Garbler,
    active_input_labels,
    decode_output_labels,
    derive_zero_labels,
    evaluate_stream,
    fresh_delta,
    fresh_seed,
)
from snail_common.net.errors import ProtocolError
from snail_common.ot import BaseReceiver, BaseSender, ExtReceiver, ExtSender
from snail_common.ot.blocks import transpose
from snail_common.ot.iknp import BLOCK

U64 = np.uint64


def seeded(seed: int):
    """A deterministic stand-in for secrets.token_bytes."""
    return random.Random(seed).randbytes


def blocks(rng: np.random.Generator, m: int) -> np.ndarray:
    return rng.integers(0, 1 << 63, size=(m, 2), dtype=np.int64).astype(U64) * U64(3)


def session(r_seed: int = 1, s_seed: int = 2, max_batch: int | None = None
            ) -> tuple[ExtReceiver, ExtSender, list[dict]]:
    """A receiver and a sender with their base OTs done; the messages each received."""
    kw = {} if max_batch is None else {"max_batch": max_batch}
    receiver, sender = ExtReceiver(seeded(r_seed), **kw), ExtSender(seeded(s_seed), **kw)
    a = receiver.start()
    b = sender.base_reply(a)
    receiver.base_done(b)
    return receiver, sender, [a, b]


def chosen(x0: np.ndarray, x1: np.ndarray, r: np.ndarray) -> np.ndarray:
    return np.where(r.astype(bool)[:, None], x1, x0)


# --- the bit-matrix transpose ----------------------------------------------------------

@pytest.mark.parametrize("nbytes", [1, 2, 16, 17, 1250])
def test_transpose_matches_the_bitwise_definition(nbytes):
    rows = np.random.default_rng(nbytes).integers(0, 256, (128, nbytes), dtype=np.uint8)
    bits = np.unpackbits(rows, axis=1, bitorder="little")  # bits[i, j] = bit j of row i
    cols = np.unpackbits(transpose(rows).view(np.uint8), axis=1, bitorder="little")
    assert np.array_equal(cols, bits.T)


# --- base OTs --------------------------------------------------------------------------

def test_base_ot_receiver_gets_exactly_its_chosen_keys():
    c = np.random.default_rng(5).integers(0, 2, 128)
    sender, receiver = BaseSender(128), BaseReceiver(c)
    keys0, keys1 = sender.finish(receiver.reply(sender.first()))
    for i, bit in enumerate(c):
        assert receiver.keys[i] == (keys1 if bit else keys0)[i]
        assert receiver.keys[i] != (keys0 if bit else keys1)[i]
    assert len(set(keys0 + keys1)) == 256  # every key distinct


def test_base_ot_sender_view_is_independent_of_the_choice_bits():
    """Perfect receiver privacy, shown exactly: for any two choice vectors there is receiver
    randomness (b_i, or b_i - a where the choice is 1) that makes the sender's whole view,
    and so its keys, byte-identical. B_i = b_iG + c_iA is a uniform point whatever c_i."""
    sender_bytes = random.Random(7).randbytes(64)
    a = sodium.crypto_core_ed25519_scalar_reduce(sender_bytes)
    bs = [sodium.crypto_core_ed25519_scalar_reduce(random.Random(100 + i).randbytes(64))
          for i in range(128)]

    def run(c):
        draws = iter(b if not bit else sodium.crypto_core_ed25519_scalar_sub(b, a)
                     for b, bit in zip(bs, c))
        receiver = BaseReceiver(c, lambda n: next(draws) + bytes(n - 32))
        sender = BaseSender(128, lambda n: sender_bytes)
        reply = receiver.reply(sender.first())
        return reply, sender.finish(reply), receiver.keys

    c1 = np.random.default_rng(1).integers(0, 2, 128)
    c2 = 1 - c1
    view1, keys_s1, keys_r1 = run(c1)
    view2, keys_s2, keys_r2 = run(c2)
    assert view1 == view2 and keys_s1 == keys_s2
    assert keys_r1 != keys_r2  # the receivers did learn different keys
    assert all(k == keys_s1[bit][i] for i, (k, bit) in enumerate(zip(keys_r2, c2)))


# --- IKNP extension: correctness -------------------------------------------------------

@pytest.mark.parametrize("m", [1, 127, 128, 129, 10_000])
def test_extension_receiver_gets_exactly_its_chosen_messages(m):
    rng = np.random.default_rng(m)
    receiver, sender, _ = session(r_seed=m, s_seed=m + 1)
    r = rng.integers(0, 2, m)
    x0, x1 = blocks(rng, m), blocks(rng, m)
    out = receiver.receive(sender.respond_chosen(receiver.request(r), x0, x1))
    assert out.shape == (m, 2) and out.dtype == U64
    assert np.array_equal(out, chosen(x0, x1, r))
    assert not (out == chosen(x1, x0, r)).all(axis=1).any()


@pytest.mark.parametrize("m", [1, 127, 128, 129, 10_000])
def test_correlated_extension_gives_x0_xor_choice_times_delta(m):
    rng = np.random.default_rng(m)
    receiver, sender, _ = session()
    r = rng.integers(0, 2, m)
    delta = blocks(rng, 1)[0] | U64(1)
    answer, x0 = sender.respond_correlated(receiver.request(r), delta)
    out = receiver.receive(answer)
    assert np.array_equal(out, chosen(x0, x0 ^ delta, r))
    assert len(answer["w"]) == BLOCK * m  # one block per OT, half of chosen OT
    assert len(np.unique(x0, axis=0)) == m  # the zero-messages are distinct random blocks


def test_batches_continue_one_session():
    """Several batches after one base-OT phase: indices run on, each batch is correct."""
    rng = np.random.default_rng(3)
    receiver, sender, _ = session()
    starts = []
    for m in (129, 1, 1000, 64):
        r = rng.integers(0, 2, m)
        x0, x1 = blocks(rng, m), blocks(rng, m)
        request = receiver.request(r)
        starts.append(request["start"])
        assert np.array_equal(receiver.receive(sender.respond_chosen(request, x0, x1)),
                              chosen(x0, x1, r))
    assert starts == [0, 129, 130, 1130]


def test_same_choices_in_two_batches_give_unrelated_transcripts():
    """The PRG streams run on: a batch never reuses the pads of an earlier one."""
    receiver, sender, _ = session()
    r = np.ones(256, dtype=int)
    u1 = receiver.request(r)
    receiver.receive(sender.respond_chosen(u1, bytes(BLOCK * 256), bytes(BLOCK * 256)))
    u2 = receiver.request(r)
    y2 = sender.respond_chosen(u2, bytes(BLOCK * 256), bytes(BLOCK * 256))
    assert u1["u"] != u2["u"]
    assert not set(np.frombuffer(u1["u"], U64)) & set(np.frombuffer(u2["u"], U64))
    assert len(set(np.frombuffer(y2["y"], U64))) > 1000


def wire_trip(msg: dict) -> dict:
    """A message as it arrives after msgpack (what the daemons' frames carry)."""
    return msgpack.unpackb(msgpack.packb(msg), raw=False)


def test_map_owner_input_by_ot_garbles_to_the_cleartext_result():
    """FP-mul with the device's operand from its seed and D and the map owner's operand
    through OT from the garbler (sender: (L0, L0 ^ D) per wire; receiver: the map owner's
    bits), every OT message through msgpack: the decoded output equals cleartext."""
    schedule = schedule_circuit(load_bristol(BRISTOL / "FP-mul.txt"))
    device = np.frombuffer(np.array([3.25]).tobytes(), np.uint8)
    owner = np.frombuffer(np.array([-7.5e2]).tobytes(), np.uint8)
    bits = np.unpackbits(np.concatenate([device, owner]), bitorder="little").astype(bool)
    seed, delta = fresh_seed(), fresh_delta()
    garbler = Garbler(schedule, seed, delta)
    owner_slots = slice(2 + 64, 2 + 128)  # slots 0 and 1 are the constants

    map_owner, garbler_ot = ExtReceiver(), ExtSender()
    to_owner = [wire_trip(garbler_ot.base_reply(wire_trip(map_owner.start())))]
    map_owner.base_done(to_owner[0])
    request = wire_trip(map_owner.request(bits[64:]))
    zero = derive_zero_labels(seed, schedule.n_inputs + 2)[owner_slots]
    to_owner.append(wire_trip(garbler_ot.respond_chosen(request, zero, zero ^ delta)))
    owner_labels = map_owner.receive(to_owner[1])
    # nothing the map owner receives holds D or the seed, or a label it did not choose
    unchosen = np.where(bits[64:, None], zero, zero ^ delta).tobytes()
    for secret in [delta.tobytes(), seed] + [unchosen[i:i + 16] for i in range(0, 1024, 16)]:
        assert not any(secret in value for msg in to_owner for value in msg.values()
                       if isinstance(value, bytes))
    labels = active_input_labels(seed, delta, np.r_[bits[:64], np.zeros(64, bool)])
    labels[owner_slots] = owner_labels  # what the map owner sends the evaluator
    active = evaluate_stream(schedule, labels, garbler.frames())
    out = decode_output_labels(delta, garbler.output_zero_labels, active)
    assert np.array_equal(out, evaluate_bits(schedule, bits).reshape(-1))
    assert np.packbits(out, bitorder="little").view(np.float64)[0] == 3.25 * -7.5e2


# --- what each side sees ---------------------------------------------------------------

def test_receiver_sees_the_unchosen_message_only_under_a_pad_it_cannot_compute():
    """Same randomness on both sides, different unchosen messages: everything the receiver
    sees and outputs is byte-identical except the unchosen halves of ``y``, which differ by
    exactly the change of message. The pad over them is not the receiver's pad H(j, t_j)
    (the only one it can compute: the other is H(j, t_j ^ s) and s is the sender's)."""
    m = 1000
    rng = np.random.default_rng(11)
    r = rng.integers(0, 2, m)
    x0, x1 = blocks(rng, m), blocks(rng, m)
    other0, other1 = blocks(rng, m), blocks(rng, m)

    def run(y0, y1):
        receiver, sender, seen = session(r_seed=21, s_seed=22)
        answer = sender.respond_chosen(receiver.request(r), y0, y1)
        return seen, answer, receiver.receive(answer)

    pick = r.astype(bool)
    seen1, ans1, out1 = run(x0, x1)
    seen2, ans2, out2 = run(np.where(pick[:, None], other0, x0),
                            np.where(pick[:, None], x1, other1))
    assert seen1 == seen2 and np.array_equal(out1, out2)
    y1 = np.frombuffer(ans1["y"], U64).reshape(m, 2, 2)
    y2 = np.frombuffer(ans2["y"], U64).reshape(m, 2, 2)
    idx, chosen_side, other_side = np.arange(m), r.astype(np.intp), 1 - r.astype(np.intp)
    assert np.array_equal(y1[idx, chosen_side], y2[idx, chosen_side])
    unchosen1, unchosen2 = chosen(x1, x0, r), np.where(pick[:, None], other0, other1)
    assert np.array_equal(y1[idx, other_side] ^ y2[idx, other_side], unchosen1 ^ unchosen2)
    own_pad = y1[idx, chosen_side] ^ out1
    other_pad = y1[idx, other_side] ^ unchosen1
    assert not (own_pad == other_pad).all(axis=1).any()
    assert not (other_pad == 0).all(axis=1).any()


def test_receiver_sees_delta_only_under_a_pad_it_cannot_compute():
    """Correlated OT: changing the sender's Delta changes only w, by exactly the change."""
    m = 500
    r = np.random.default_rng(4).integers(0, 2, m)

    def run(delta):
        receiver, sender, seen = session(r_seed=31, s_seed=32)
        answer, x0 = sender.respond_correlated(receiver.request(r), delta)
        return seen, answer, x0

    d1, d2 = np.array([3, 5], U64), np.array([0x1234567, 99], U64)
    seen1, ans1, x1 = run(d1)
    seen2, ans2, x2 = run(d2)
    assert seen1 == seen2 and np.array_equal(x1, x2)
    w1, w2 = (np.frombuffer(a["w"], U64).reshape(m, 2) for a in (ans1, ans2))
    assert (w1 ^ w2 == d1 ^ d2).all()
    assert not (w1 == d1).all(axis=1).any()  # w is not Delta in the clear


def test_sender_sees_the_choice_bits_only_under_a_pad_it_cannot_compute():
    """Same randomness, different choice bits: the sender's view differs only in u, each
    row by exactly r ^ r'. Row i is G(k_i^0) ^ G(k_i^1) ^ r and the sender holds only
    k_i^{s_i}: stripping its own stream leaves G(k_i^{1-s_i}) ^ r, never r."""
    m = 1024
    rng = np.random.default_rng(8)
    r1, r2 = rng.integers(0, 2, m), rng.integers(0, 2, m)

    def run(r):
        receiver, sender, seen = session(r_seed=41, s_seed=42)
        return seen, receiver.request(r), sender

    seen1, u1, sender1 = run(r1)
    seen2, u2, _ = run(r2)
    assert seen1[0] == seen2[0]  # ot_base_a: the sender's only other received message
    assert {k: v for k, v in u1.items() if k != "u"} == {k: v for k, v in u2.items()
                                                          if k != "u"}
    rows1, rows2 = (np.frombuffer(u["u"], np.uint8).reshape(128, m // 8) for u in (u1, u2))
    diff = np.packbits((r1 ^ r2).astype(np.uint8), bitorder="little")
    assert (rows1 ^ rows2 == diff).all()
    own = sender1._streams.take(m // 8)  # the stream the sender can compute
    stripped = rows1 ^ own
    packed = np.packbits(r1.astype(np.uint8), bitorder="little")
    assert not (stripped == packed).all(axis=1).any()


# --- malformed and out-of-bounds messages ----------------------------------------------

def small_order_point() -> bytes:
    return bytes.fromhex("c7176a703d4dd84fba3c0b760d10670f2a2053fa2c39ccc64ec7fd7792ac03fa")


def expect(code: str, field: str, fn, *args):
    with pytest.raises(ProtocolError) as info:
        fn(*args)
    assert info.value.code == code, info.value
    assert repr(field) in info.value.message or field in info.value.message, info.value


@pytest.mark.parametrize(("msg", "code", "field"), [
    ("not a map", "malformed", "map"),
    ({"t": "ot_base_b", "a": bytes(32)}, "unexpected", "'t'"),
    ({"t": "ot_base_a"}, "missing_field", "a"),
    ({"t": "ot_base_a", "a": bytes(32), "x": 1}, "unknown_field", "x"),
    ({"t": "ot_base_a", "a": "text"}, "malformed", "a"),
    ({"t": "ot_base_a", "a": bytes(31)}, "malformed", "a"),
    ({"t": "ot_base_a", "a": bytes(32)}, "bad_request", "a"),  # not on the curve
    ({"t": "ot_base_a", "a": small_order_point()}, "bad_request", "a"),
    ({"t": "ot_base_a", "a": b"\x01" + bytes(31)}, "bad_request", "a"),  # the identity
])
def test_bad_base_a_is_a_named_error(msg, code, field):
    expect(code, field, ExtSender().base_reply, msg)


def test_bad_base_b_is_a_named_error():
    receiver, sender = ExtReceiver(), ExtSender()
    good = sender.base_reply(receiver.start())["b"]
    torsion = sodium.crypto_core_ed25519_add(good[32 * 5:32 * 6], small_order_point())
    bad = good[:32 * 5] + torsion + good[32 * 6:]
    expect("bad_request", "b[5]", receiver.base_done, {"t": "ot_base_b", "b": bad})
    expect("malformed", "b", ExtReceiver().base_done, {"t": "ot_base_b", "b": good[:-1]})
    expect("malformed", "b", ExtReceiver().base_done, {"t": "ot_base_b", "b": [good]})


def test_bad_extension_requests_are_named_errors():
    receiver, sender, _ = session(max_batch=1000)
    u = receiver.request(np.ones(100, dtype=int))
    fn = sender.respond_correlated
    delta = bytes(16)
    expect("bad_request", "m", fn, {**u, "m": 1001}, delta)  # more OTs than the bound
    expect("bad_request", "m", fn, {**u, "m": 1 << 40}, delta)  # refused before any work
    expect("bad_request", "m", fn, {**u, "m": 0}, delta)
    expect("malformed", "m", fn, {**u, "m": 10.0}, delta)
    expect("malformed", "m", fn, {**u, "m": True}, delta)
    expect("bad_request", "start", fn, {**u, "start": 5}, delta)
    expect("bad_request", "start", fn, {**u, "start": -1}, delta)
    expect("malformed", "u", fn, {**u, "u": u["u"][:-1]}, delta)
    expect("malformed", "u", fn, {**u, "u": u["u"] + b"\0"}, delta)
    expect("malformed", "u", fn, {**u, "m": 92}, delta)  # u no longer fits m
    expect("missing_field", "start", fn, {k: v for k, v in u.items() if k != "start"}, delta)
    expect("unexpected", "'t'", fn, {**u, "t": "ot_ext_y"}, delta)
    # the sender is still in step: the original request goes through
    out = receiver.receive(fn(u, np.array([1, 0], U64))[0])
    assert out.shape == (100, 2)


def test_bad_extension_answers_are_named_errors():
    receiver, sender, _ = session()
    expect("unexpected", "no batch", receiver.receive, {"t": "ot_ext_y", "start": 0, "y": b""})
    u = receiver.request(np.ones(10, dtype=int))
    answer = sender.respond_chosen(u, bytes(160), bytes(160))
    expect("malformed", "y", receiver.receive, {**answer, "y": answer["y"][:-16]})
    expect("bad_request", "start", receiver.receive, {**answer, "start": 3})
    expect("unknown_field", "w", receiver.receive, {**answer, "w": b""})
    expect("missing_field", "w", receiver.receive, {"t": "ot_ext_c", "start": 0})
    expect("unexpected", "'t'", receiver.receive, {**answer, "t": "ot_ext_u"})
    assert receiver.receive(answer).shape == (10, 2)


def test_messages_out_of_order_are_named_errors():
    receiver, sender = ExtReceiver(), ExtSender()
    expect("unexpected", "before the base", sender.respond_chosen,
           {"t": "ot_ext_u", "start": 0, "m": 1, "u": bytes(128)}, bytes(16), bytes(16))
    a = receiver.start()
    b = sender.base_reply(a)
    expect("unexpected", "twice", sender.base_reply, a)
    receiver.base_done(b)
    expect("unexpected", "twice", receiver.base_done, b)


def test_local_misuse_is_a_value_error():
    receiver, sender, _ = session(max_batch=64)
    for bad in (np.array([0, 2]), np.zeros((2, 2)), np.zeros(0), np.zeros(65)):
        with pytest.raises(ValueError):
            receiver.request(bad)
    u = receiver.request(np.zeros(8))
    with pytest.raises(ValueError, match="x1"):
        sender.respond_chosen(u, bytes(128), bytes(127))
    # the refused call left both in step
    assert receiver.receive(sender.respond_chosen(u, bytes(128), bytes(128))).shape == (8, 2)


def test_any_request_is_answered_or_refused_by_name():
    _, sender, _ = session(max_batch=16)  # one session: a refused request changes nothing

    @settings(max_examples=300, deadline=None)
    @given(msg=st.one_of(
        st.binary(max_size=64),
        st.dictionaries(st.sampled_from(["t", "start", "m", "u", "x"]),
                        st.one_of(st.integers(-5, 1 << 70), st.binary(max_size=300),
                                  st.sampled_from(["ot_ext_u", "ot_ext_y"]), st.none()),
                        max_size=5)))
    def run(msg):
        try:
            sender.respond_chosen(msg, bytes(16 * 16), bytes(16 * 16))
        except ProtocolError:
            pass
        except ValueError as exc:  # a valid request for another number of OTs than supplied
            assert "x0" in str(exc)

    run()


def test_any_base_or_answer_message_is_accepted_or_refused_by_name():
    """Random maps and bytes into every receiving step: a ProtocolError or success, never
    another exception (the daemons answer the error by name and drop the session)."""
    receiver, _, _ = session()
    receiver.request(np.ones(16, dtype=int))
    fresh_sender, fresh_receiver = ExtSender(), ExtReceiver()
    fresh_receiver.start()
    steps = [fresh_sender.base_reply, fresh_receiver.base_done, receiver.receive]

    @settings(max_examples=300, deadline=None)
    @given(step=st.sampled_from(steps), msg=st.one_of(
        st.binary(max_size=64), st.none(), st.integers(),
        st.dictionaries(st.sampled_from(["t", "a", "b", "start", "w", "y"]),
                        st.one_of(st.integers(-5, 1 << 70), st.binary(max_size=600),
                                  st.sampled_from(["ot_base_a", "ot_base_b", "ot_ext_y",
                                                   "ot_ext_c"]), st.none(), st.text()),
                        max_size=4)))
    def run(step, msg):
        with contextlib.suppress(ProtocolError):
            step(msg)

    run()
