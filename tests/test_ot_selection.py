"""Oblivious selection (snail_common/ot/selection.py): the device gets exactly v[idx_i] ^ P_i
per query, its keys open no other entry, and bad tables or requests are named errors."""

from __future__ import annotations

import numpy as np
import pytest

from snail_common.net.errors import ProtocolError
from snail_common.ot import ExtReceiver, ExtSender
from snail_common.ot.blocks import CorrelationRobustHash
from snail_common.ot.selection import SelectReceiver, SelectSender, index_bits


def pair() -> tuple[ExtReceiver, ExtSender]:
    receiver, sender = ExtReceiver(), ExtSender()
    receiver.base_done(sender.base_reply(receiver.start()))
    return receiver, sender


def values(rng: np.random.Generator, rows: int, width: int = 12) -> np.ndarray:
    return rng.integers(0, 256, (rows, width), dtype=np.uint8)


@pytest.mark.parametrize(("n_values", "n"), [(1, 3), (2, 5), (5, 4), (64, 6), (1000, 17)])
def test_each_query_gets_its_padded_value(n_values, n):
    rng = np.random.default_rng(n_values)
    receiver, sender = pair()
    v, pads = values(rng, n_values), values(rng, n)
    idx = rng.integers(0, n_values, n)
    device, owner = SelectReceiver(receiver, n_values, 12), SelectSender(sender, v)
    out = device.receive(owner.respond(device.request(idx), pads))
    assert np.array_equal(out, v[idx] ^ pads)
    # a second selection in the same OT session, other pads and indices
    idx2, pads2 = rng.integers(0, n_values, n), values(rng, n)
    assert np.array_equal(device.receive(owner.respond(device.request(idx2), pads2)),
                          v[idx2] ^ pads2)


def test_the_device_keys_open_no_other_entry():
    """Decrypting entry k != idx_i with the keys the device holds gives garbage: each such
    entry has a term under a key of the other OT side."""
    rng = np.random.default_rng(1)
    n_values, n = 40, 3
    receiver, sender = pair()
    v, pads = values(rng, n_values, 16), values(rng, n, 16)
    idx = np.array([0, 17, 39])
    device, owner = SelectReceiver(receiver, n_values, 16), SelectSender(sender, v)
    request = device.request(idx)
    keys = device._pending[2]  # (n, l, 2): the random-OT keys the device holds
    table_msg = owner.respond(request, pads)
    table = np.frombuffer(table_msg["table"], np.uint8).reshape(n, n_values, 16)
    hash_ = CorrelationRobustHash(table_msg["key"])
    per_query = index_bits(n_values)
    for i in range(n):
        for k in range(n_values):
            tweaks = (i * per_query + np.arange(per_query)) * n_values + k
            pad = np.bitwise_xor.reduce(hash_(keys[i], tweaks), axis=0).view(np.uint8)
            opened = table[i, k] ^ pad
            assert np.array_equal(opened, v[k] ^ pads[i]) == (k == idx[i])
    assert np.array_equal(device.receive(table_msg), v[idx] ^ pads)


def test_no_value_is_in_the_table_in_the_clear():
    """The table is all the device receives from the map owner: no entry is a 3D point,
    and none is a padded point either (each is under a hash of keys)."""
    rng = np.random.default_rng(5)
    receiver, sender = pair()
    n_values, n = 300, 8
    v, pads = values(rng, n_values), values(rng, n)
    device, owner = SelectReceiver(receiver, n_values, 12), SelectSender(sender, v)
    idx = rng.integers(0, n_values, n)
    table_msg = owner.respond(device.request(idx), pads)
    entries = {bytes(e) for e in np.frombuffer(table_msg["table"], np.uint8).reshape(-1, 12)}
    assert len(entries) == n * n_values
    assert not entries & {bytes(row) for row in v}
    assert not entries & {bytes(row) for row in (v[None] ^ pads[:, None]).reshape(-1, 12)}
    assert np.array_equal(device.receive(table_msg), v[idx] ^ pads)


def test_the_table_has_one_entry_per_value_and_query():
    receiver, sender = pair()
    device = SelectReceiver(receiver, 10_000, 12)
    request = device.request(np.arange(64) * 150)
    assert request["m"] == 64 * 14  # ceil(log2 10,000) OTs per query
    rng = np.random.default_rng(2)
    table = SelectSender(sender, values(rng, 10_000)).respond(request, values(rng, 64))
    assert len(table["table"]) == 64 * 10_000 * 12


def test_bad_tables_and_requests_are_named_errors():
    rng = np.random.default_rng(3)
    receiver, sender = pair()
    device, owner = SelectReceiver(receiver, 8, 12), SelectSender(sender, values(rng, 8))
    with pytest.raises(ProtocolError, match="no selection requested"):
        device.receive({"t": "sel_table", "start": 0, "key": bytes(16), "table": b""})
    request = device.request(np.array([1, 2]))
    for bad, field in (({**request, "m": 5}, "'m'"), ({**request, "m": 3 * 4097}, "'m'"),
                       ({**request, "m": "6"}, "'m'"), ({**request, "u": b""}, "'u'"),
                       ("nope", "map")):
        with pytest.raises(ProtocolError, match=field):
            owner.respond(bad, values(rng, 2))
    table = owner.respond(request, values(rng, 2))
    for bad, field in (({**table, "table": table["table"][:-1]}, "'table'"),
                       ({**table, "key": bytes(15)}, "'key'"),
                       ({**table, "start": 99}, "'start'"),
                       ({**table, "extra": 1}, "'extra'")):
        with pytest.raises(ProtocolError, match=field):
            device.receive(bad)
    assert device.receive(table).shape == (2, 12)


def test_local_misuse_is_a_value_error():
    receiver, sender = pair()
    device = SelectReceiver(receiver, 8, 12)
    for bad in (np.array([8]), np.array([-1]), np.array([]), np.array([1.0])):
        with pytest.raises(ValueError, match="indices"):
            device.request(bad)
    with pytest.raises(ValueError, match="values"):
        SelectSender(sender, np.zeros((8, 17), np.uint8))
    owner = SelectSender(sender, np.zeros((8, 12), np.uint8))
    with pytest.raises(ValueError, match="pads"):
        owner.respond(device.request(np.array([1])), np.zeros((2, 12), np.uint8))
