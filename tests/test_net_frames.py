"""Framing and message validation: strict decoding, incremental reading, no copies lost."""

import struct

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from snail_common.net import errors, messages
from snail_common.net.frames import (
    MAX_FRAME,
    PROTOCOL_VERSION,
    BodyPool,
    FrameReader,
    decode,
    encode,
    encode_bytes,
)

SID = bytes(range(16))
HASH = "ab" * 32


def body(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def code_of(data: bytes) -> str:
    with pytest.raises(errors.ProtocolError) as info:
        decode(data)
    return info.value.code


def sample_messages():
    return [
        messages.make("hello", role="client", software="t", max_frame=MAX_FRAME),
        messages.make("session_start", sid=SID, circuit="ops/fadd-x4", hash=HASH),
        messages.make("garble_request", sid=SID, circuit="ops/fadd-x4", hash=HASH,
                      seed=bytes(16), delta=b"\x01" + bytes(15), key=bytes(16)),
        messages.make("input_labels", sid=SID, start=0, total=3, labels=bytes(48)),
        messages.make("tables", sid=SID, data=bytes(range(256)) * 300),
        messages.make("stats", sid=SID, traffic={"garbler_to_evaluator": 5},
                      timing={"garble_s": 0.5}),
        messages.make("health", role="evaluator", sessions={"active": 1}, uptime_s=1.0),
        messages.error("timeout", "slow", SID),
        messages.make("bye"),
    ]


def test_roundtrip_of_every_sample_and_big_binaries_are_separate_buffers():
    for msg in sample_messages():
        frame = encode_bytes(msg)
        (length,) = struct.unpack(">I", frame[:4])
        assert length == len(frame) - 4
        assert decode(frame[4:]) == msg
    tables = sample_messages()[4]
    parts = encode(tables)
    assert any(p is tables["data"] for p in parts)  # not copied into the frame
    assert b"".join(parts)[4:] == body({"v": PROTOCOL_VERSION, **tables})


@pytest.mark.parametrize("data, code", [
    (b"\xc1", errors.MALFORMED),  # never-used msgpack byte
    (body([1, 2]), errors.MALFORMED),  # not a map
    (body({"v": 1, "t": "bye"})[:-1], errors.MALFORMED),  # truncated
    (body({"v": 1, "t": "bye"}) + b"\x00", errors.MALFORMED),  # trailing bytes
    (body({"t": "bye"}), errors.VERSION),
    (body({"v": 99, "t": "bye"}), errors.VERSION),
    (body({"v": 1}), errors.MISSING_FIELD),
    (body({"v": 1, "t": "launch"}), errors.UNKNOWN_TYPE),
    (body({"v": 1, "t": "done"}), errors.MISSING_FIELD),
    (body({"v": 1, "t": "bye", "extra": 1}), errors.UNKNOWN_FIELD),
    (body({"v": 1, "t": "done", "sid": "0123456789abcdef"}), errors.MALFORMED),  # str
    (body({"v": 1, "t": "done", "sid": bytes(15)}), errors.MALFORMED),
    (body({"v": 1, "t": "input_labels", "sid": SID, "start": -1, "total": 1,
           "labels": bytes(16)}), errors.MALFORMED),
    (body({"v": 1, "t": "input_labels", "sid": SID, "start": 0, "total": 1,
           "labels": bytes(15)}), errors.MALFORMED),
    (body({"v": 1, "t": "session_start", "sid": SID, "circuit": "x", "hash": "AB" * 32}),
     errors.MALFORMED),
    (body({"v": 1, "t": "hello", "role": "admin", "software": "x", "max_frame": 1}),
     errors.MALFORMED),
    (body({"v": 1, "t": "stats", "sid": SID, "traffic": {"a": 1.5}, "timing": {}}),
     errors.MALFORMED),
    (body({"v": 1, "t": "stats", "sid": SID, "traffic": {}, "timing": {"a": float("nan")}}),
     errors.MALFORMED),
    (body({"v": 1, "t": "done", "sid": msgpack.ExtType(1, SID)}), errors.MALFORMED),
    (body({"v": 1, "t": "bye", 5: 1}), errors.MALFORMED),  # non-string key
    (b"\x82\xa1v\x01\xa1v\x01", errors.MALFORMED),  # duplicate key
])
def test_strict_decoding_names_the_problem(data, code):
    assert code_of(data) == code


def test_error_messages_name_the_field():
    with pytest.raises(errors.ProtocolError, match="'sid'"):
        decode(body({"v": 1, "t": "done", "sid": bytes(3)}))
    with pytest.raises(errors.ProtocolError, match="lacks field 'hash'"):
        decode(body({"v": 1, "t": "session_start", "sid": SID, "circuit": "x"}))


def test_timestamps_and_pickle_like_payloads_are_rejected():
    ts = msgpack.packb({"v": 1, "t": "done", "sid": msgpack.Timestamp(1, 0)})
    assert code_of(ts) == errors.MALFORMED
    pickled = b"\x80\x04\x95" + bytes(20)  # a pickle stream is not msgpack we accept
    assert code_of(pickled) == errors.MALFORMED


def test_encode_refuses_oversized_frames():
    with pytest.raises(errors.ProtocolError) as info:
        encode(messages.make("tables", sid=SID, data=bytes(MAX_FRAME)))
    assert info.value.code == errors.OVERSIZE


def feed(reader: FrameReader, stream: bytes, cuts: list[int]) -> list:
    """Write ``stream`` through reader.buffer() in pieces of the given sizes."""
    out, pos = [], 0
    sizes = iter(cuts)
    while pos < len(stream):
        buf = reader.buffer()
        n = min(len(buf), len(stream) - pos, max(1, next(sizes, len(stream))))
        buf[:n] = stream[pos : pos + n]
        buf.release()
        pos += n
        out += [m for m, _ in reader.filled(n)]
    return out


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(0, 8), min_size=1, max_size=12),
       st.lists(st.integers(1, 300_000), max_size=40))
def test_reader_reassembles_frames_cut_anywhere(picks, cuts):
    pool = sample_messages()
    sent = [pool[i] for i in picks]
    stream = b"".join(encode_bytes(m) for m in sent)
    reader = FrameReader()
    assert feed(reader, stream, cuts) == sent
    assert not reader.partial


def test_reader_refuses_an_oversized_frame_from_its_header():
    reader = FrameReader(max_frame=1000)
    buf = reader.buffer()
    buf[:4] = struct.pack(">I", 1001)
    buf.release()
    with pytest.raises(errors.ProtocolError) as info:
        reader.filled(4)
    assert info.value.code == errors.OVERSIZE


def test_reader_reports_a_partial_frame():
    frame = encode_bytes(sample_messages()[4])
    reader = FrameReader()
    feed(reader, frame[:-1], [])
    assert reader.partial


def _feed(reader: FrameReader, data: bytes) -> list:
    """Write ``data`` through the reader's buffers as a transport would."""
    out, pos = [], 0
    while pos < len(data):
        buf = reader.buffer()
        n = min(len(buf), len(data) - pos)
        buf[:n] = data[pos : pos + n]
        pos += n
        out += reader.filled(n)
    return out


def test_a_frame_of_millions_of_tiny_objects_is_refused_while_small():
    """Four million empty maps in 4 MiB: refused after a handful of containers, with
    bounded allocation, and the refusal keeps nothing of what was decoded."""
    import gc
    import tracemalloc

    body = b"\xdd" + (4_000_000).to_bytes(4, "big") + b"\x80" * 4_000_000  # array32
    frame = struct.pack(">I", len(body)) + body
    tracemalloc.start()
    try:
        with pytest.raises(errors.ProtocolError) as caught:
            _feed(FrameReader(), frame)
        _, peak = tracemalloc.get_traced_memory()
        exc = caught.value
        del caught
        gc.collect()
        held, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert exc.code == errors.MALFORMED
    assert peak < 32 << 20, f"decoding allocated {peak >> 20} MiB"  # the frame's buffers
    assert held < 12 << 20, f"the refusal holds {held >> 20} MiB"
    assert exc.__traceback__ is None or all(
        "msg" not in tb.tb_frame.f_locals for tb in _walk(exc.__traceback__))


def _walk(tb):
    while tb is not None:
        yield tb
        tb = tb.tb_next


@pytest.mark.parametrize("bad", [
    {"t": "health_request", "x": [[1] * 60] * 60},  # many lists
    {"t": "health_request", "x": list(range(65))},  # a long list
    {"t": "health_request", "x": {str(i): i for i in range(33)}},  # a big map
    {"t": "error", "code": "x", "message": "y" * 5000},  # a long string
])
def test_containers_and_strings_are_bounded_by_the_catalogue(bad):
    body = msgpack.packb({"v": 1, **bad}, use_bin_type=True)
    with pytest.raises(errors.ProtocolError) as caught:
        decode(body)
    assert caught.value.code == errors.MALFORMED


def test_a_big_frame_header_alone_does_not_allocate_its_body():
    """A header announcing 4 MiB and a few bytes of body: the reader holds what arrived
    (rounded up to its small-buffer size), not what was announced."""
    reader = FrameReader()
    _feed(reader, struct.pack(">I", 4 << 20) + b"x" * 100)
    assert len(reader._big) <= FrameReader.SMALL
    assert reader.partial


def _big_tables(fill: int, size: int = 300_000) -> dict:
    return messages.make("tables", sid=SID, data=bytes([fill]) * size)


def test_big_tables_are_views_of_the_receive_buffer_and_recycled_buffers_are_reused():
    """A large ``tables`` frame is handed over as a view of the buffer TLS wrote it to
    (no msgpack copy); frames still held keep their bytes while later ones arrive, and a
    buffer handed back with ``recycle`` receives a later frame instead of fresh memory."""
    reader = FrameReader()
    first, second = _big_tables(1), _big_tables(2)
    (a,) = [m for m, _ in _feed(reader, encode_bytes(first))]
    (b,) = [m for m, _ in _feed(reader, encode_bytes(second))]
    assert isinstance(a["data"], memoryview) and isinstance(b["data"], memoryview)
    assert a["data"].obj is not b["data"].obj
    assert a == first and b == second  # the first frame was not overwritten by the second
    buffer = a["data"].obj
    reader.recycle(a["data"])
    (c,) = [m for m, _ in _feed(reader, encode_bytes(_big_tables(3)))]
    assert c["data"].obj is buffer and c == _big_tables(3)
    assert b == second


def test_only_tables_are_lent_and_lifted_fields_are_still_checked():
    """Other large frames (labels) are copied as before; a lifted field is validated and a
    repeated key refused just as when msgpack decodes it whole."""
    labels = messages.make("input_labels", sid=SID, start=0, total=20_000,
                           labels=bytes(16 * 20_000))
    (got,) = [m for m, _ in _feed(FrameReader(), encode_bytes(labels))]
    assert isinstance(got["labels"], bytes) and got == labels
    big = b"\xc6" + (100_000).to_bytes(4, "big") + bytes(100_000)
    head = body({"v": 1, "t": "tables", "sid": SID})
    for bad, code in [
        (bytes([head[0] + 1]) + head[1:] + body("data") + big + body("data") + big,
         errors.MALFORMED),  # "data" twice: one map entry too many
        (bytes([head[0] + 2]) + head[1:] + body("data") + big + body("junk") + big,
         errors.UNKNOWN_FIELD),
        (body({"v": 1, "t": "tables", "data": b""})[:-2] + big, errors.MISSING_FIELD),
    ]:
        with pytest.raises(errors.ProtocolError) as info:
            _feed(FrameReader(), struct.pack(">I", len(bad)) + bad)
        assert info.value.code == code


def test_a_shared_pool_hands_recycled_bodies_to_other_connections_within_its_limit():
    """Readers sharing a BodyPool (a daemon's connections) receive into bodies another one
    recycled, the closest fit first and never one over twice the frame; the pool keeps
    at most its limit in bytes."""
    pool = BodyPool(limit=2 << 20)
    one, two = FrameReader(pool=pool), FrameReader(pool=pool)
    (small,) = [m for m, _ in _feed(one, encode_bytes(_big_tables(1, 300_000)))]
    (large,) = [m for m, _ in _feed(one, encode_bytes(_big_tables(2, 900_000)))]
    one.recycle(large["data"])
    one.recycle(small["data"])
    assert pool.held == len(small["data"].obj) + len(large["data"].obj)
    (got,) = [m for m, _ in _feed(two, encode_bytes(_big_tables(3, 290_000)))]
    assert got["data"].obj is small["data"].obj and got == _big_tables(3, 290_000)
    (got,) = [m for m, _ in _feed(two, encode_bytes(_big_tables(4, 800_000)))]
    assert got["data"].obj is large["data"].obj and got == _big_tables(4, 800_000)
    assert pool.held == 0
    pool.give(bytearray(1 << 20))
    (got,) = [m for m, _ in _feed(two, encode_bytes(_big_tables(5, 300_000)))]
    assert len(got["data"].obj) < 1 << 19  # not the kept 1 MiB: at most twice its size
    assert pool.held == 1 << 20
    full = BodyPool(limit=1 << 20)
    full.give(bytearray(600_000))
    full.give(bytearray(600_000))  # over the limit: let go
    assert full.held == 600_000


class _Recorder:
    """A transport that records what it is given, call by call."""

    def __init__(self) -> None:
        self.calls: list[list] = []

    def get_extra_info(self, name, default=None):
        return default

    def set_write_buffer_limits(self, high=None, low=None) -> None:
        pass

    def is_closing(self) -> bool:
        return False

    def write(self, data) -> None:
        self.calls.append([data])

    def writelines(self, parts) -> None:
        self.calls.append(list(parts))


def test_a_frame_reaches_the_transport_in_one_call_with_its_data_uncopied():
    """Length, header and table data in one transport call: TLS then makes one socket
    write per frame instead of three (two of them a few bytes long)."""
    from snail_common.net.conn import Connection

    conn, transport = Connection(), _Recorder()
    conn.connection_made(transport)
    msg = messages.make("tables", sid=SID, data=memoryview(bytes(range(256)) * 300))
    size = conn.write(msg)
    (call,) = transport.calls
    assert b"".join(call) == encode_bytes(msg) and size == len(encode_bytes(msg))
    assert any(part is msg["data"] for part in call)


def test_a_daemon_lets_its_recycled_bodies_go_once_idle(monkeypatch):
    """Back-to-back sessions keep the pool; a daemon idle for BODIES_IDLE_S holds none of
    it (its memory follows its load)."""
    import asyncio
    import logging

    from snail_common.net import service

    monkeypatch.setattr(service, "BODIES_IDLE_S", 0.05)
    record = {"sid": SID, "circuit": "c", "n_and": 1, "bytes_in": 0, "bytes_out": 0,
              "seconds": 0.0, "outcome": "ok"}

    async def run() -> tuple[int, int]:
        daemon = service.Daemon(service.Options(workers=1), logging.getLogger("test"))
        daemon.bodies.give(bytearray(1 << 20))
        daemon.finish(daemon.admit(), record)  # idle now ...
        slot = daemon.admit()  # ... but the next session starts at once
        await asyncio.sleep(0.1)
        kept = daemon.bodies.held
        daemon.finish(slot, record)
        await asyncio.sleep(0.1)
        daemon.pool.shutdown()
        return kept, daemon.bodies.held

    assert asyncio.run(run()) == (1 << 20, 0)
