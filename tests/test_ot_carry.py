"""Carrying the map-owner protocol's blobs and labels: chunks put back strictly in order,
pad bits in the circuit's wire order, and the evaluator's bounded wait for map-owner
labels that come before their session."""

from __future__ import annotations

import numpy as np
import pytest

from snail_common.circuit.values import to_bits
from snail_common.net.errors import ProtocolError
from snail_common.ot.carry import BlobAssembler, as_words, chunks, pad_bits
from snail_evaluator.owner import EarlyOwnerLabels


def test_chunks_reassemble_in_order_only():
    data = bytes(range(256)) * 41
    pieces = list(chunks(data, 1000))
    assert [o for o, _ in pieces] == list(range(0, len(data), 1000))
    blob = BlobAssembler("t", len(data), 1 << 20)
    for offset, piece in pieces:
        assert not blob.complete
        blob.add(offset, piece)
    assert blob.complete and blob.data() == data
    assert list(chunks(b"")) == [(0, b"")]
    out_of_order = BlobAssembler("sel_table", len(data), 1 << 20)
    with pytest.raises(ProtocolError, match="sel_table: a piece at offset 1000"):
        out_of_order.add(*pieces[1])
    with pytest.raises(ProtocolError, match="at most 10"):
        BlobAssembler("sel_table", 11, 10)
    over = BlobAssembler("t", 4, 10)
    with pytest.raises(ProtocolError):
        over.add(0, b"12345")


def test_pad_bits_follow_the_circuits_wire_order():
    rng = np.random.default_rng(1)
    rows = rng.integers(0, 256, (5, 12), dtype=np.uint8)
    words = as_words(rows)
    assert words.shape == (5, 3) and words.dtype == np.uint32
    assert np.array_equal(pad_bits(rows), to_bits(words, 32, "uint32").reshape(-1))


def _labels(sid: bytes, n: int) -> tuple[dict, int]:
    return {"t": "owner_labels", "sid": sid, "start": 0, "total": n,
            "labels": bytes(16 * n)}, 16 * n + 40


def test_early_owner_labels_are_bounded_and_dropped_oldest_first():
    early = EarlyOwnerLabels(limit=3000)
    for i in range(3):
        early.add(*_labels(bytes([i]) * 16, 50))  # 840 bytes each
    early.add(*_labels(bytes([3]) * 16, 50))  # over the limit: the oldest goes
    assert early.take(bytes([0]) * 16) == []
    assert len(early.take(bytes([1]) * 16)) == 1
    early.drop(bytes([2]) * 16)
    assert early.bytes == 840
    assert len(early.take(bytes([3]) * 16)) == 1 and early.bytes == 0
