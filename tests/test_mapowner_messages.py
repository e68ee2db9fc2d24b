"""The map-owner role: its certificate, and the messages of its protocol, each field
checked and bounded like the rest of the catalogue."""

import socket
import threading

import pytest

from snail_common.net import errors, messages, tls
from snail_common.net.frames import decode, encode_bytes

SID = bytes(range(16))
FRAME = bytes(range(16, 32))


def samples():
    return [
        messages.make("map_info_request"),
        messages.make("map_info", points=3, transform=bytes(32), start=0, ids=bytes(12)),
        messages.make("ot_base_a", a=bytes(32)),
        messages.make("ot_base_b", b=bytes(128 * 32)),
        messages.make("ot_ext_u", start=0, m=8, u=bytes(128)),
        messages.make("ot_ext_u", sid=SID, start=0, m=8, u=bytes(128)),
        messages.make("ot_ext_y", sid=SID, start=0, y=bytes(256)),
        messages.make("sel_table", frame=FRAME, start=0, key=bytes(16), offset=0, total=24,
                      table=bytes(24)),
        messages.make("map_invocation", sid=SID, count=96, evaluator="localhost:4000"),
        messages.make("pad_correction_request", frame=FRAME, sid=SID),
        messages.make("pad_correction", sid=SID, correction=bytes(12)),
        messages.make("owner_labels", sid=SID, start=0, total=2, labels=bytes(32)),
        messages.make("garble_request", sid=SID, circuit="loc/x", hash="ab" * 32,
                      seed=bytes(16), delta=b"\x01" + bytes(15), key=bytes(16),
                      map_owner="localhost:4001"),
        messages.make("hello", role="mapowner", software="t", max_frame=1),
    ]


def test_every_map_owner_message_round_trips():
    for msg in samples():
        assert decode(encode_bytes(msg)[4:]) == msg


@pytest.mark.parametrize("kind, fields, name", [
    ("map_info", {"points": 3, "transform": bytes(31), "start": 0, "ids": b""}, "transform"),
    ("map_info", {"points": 3, "transform": bytes(32), "start": 0, "ids": bytes(5)}, "ids"),
    ("map_info", {"points": 3, "transform": bytes(32), "start": 0,
                  "ids": bytes(messages.DATA_CHUNK + 4)}, "ids"),
    ("ot_base_a", {"a": bytes(33)}, "a"),
    ("ot_base_b", {"b": bytes(127 * 32)}, "b"),
    ("ot_ext_u", {"start": -1, "m": 8, "u": bytes(128)}, "start"),
    ("ot_ext_u", {"start": 0, "m": 8, "u": bytes(messages.MAX_OT_BYTES + 1)}, "u"),
    ("ot_ext_y", {"start": 0, "y": "text"}, "y"),
    ("sel_table", {"frame": bytes(15), "start": 0, "key": bytes(16), "offset": 0,
                   "total": 1, "table": b"x"}, "frame"),
    ("sel_table", {"frame": FRAME, "start": 0, "key": bytes(16), "offset": 0, "total": 1,
                   "table": bytes(messages.DATA_CHUNK + 1)}, "table"),
    ("map_invocation", {"sid": SID, "count": 96, "evaluator": "x" * 301}, "evaluator"),
    ("map_invocation", {"sid": SID, "count": 1.5, "evaluator": "h:1"}, "count"),
    ("pad_correction_request", {"frame": bytes(15), "sid": SID}, "frame"),
    ("pad_correction", {"sid": SID, "correction": "bits"}, "correction"),
    ("owner_labels", {"sid": SID, "start": 0, "total": 1, "labels": bytes(15)}, "labels"),
])
def test_bad_fields_are_named(kind, fields, name):
    with pytest.raises(errors.ProtocolError) as caught:
        messages.validate({"t": kind, **fields})
    assert repr(name) in caught.value.message


def test_unknown_fields_and_missing_fields_are_refused():
    with pytest.raises(errors.ProtocolError) as caught:
        messages.validate({"t": "map_invocation", "sid": SID, "count": 1,
                           "evaluator": "h:1", "pose": [0.0]})
    assert caught.value.code == errors.UNKNOWN_FIELD
    with pytest.raises(errors.ProtocolError) as caught:
        messages.validate({"t": "owner_labels", "sid": SID, "start": 0, "total": 1})
    assert caught.value.code == errors.MISSING_FIELD
    with pytest.raises(errors.ProtocolError) as caught:  # the frame is named per run now
        messages.validate({"t": "map_invocation", "sid": SID, "frame": FRAME, "count": 96,
                           "evaluator": "h:1"})
    assert caught.value.code == errors.UNKNOWN_FIELD and "'frame'" in caught.value.message


def test_make_certs_issues_a_map_owner_server_certificate(tmp_path):
    tls.make_certs(tmp_path)
    assert tls.cert_path(tmp_path, "mapowner").is_file()
    server = tls.server_context(tmp_path, "mapowner")
    client = tls.client_context(tmp_path, "garbler")
    a, b = socket.socketpair()
    roles = {}

    def serve():
        with server.wrap_socket(a, server_side=True) as s:
            roles["peer"] = tls.peer_identity(s).role

    t = threading.Thread(target=serve)
    t.start()
    with client.wrap_socket(b, server_hostname="localhost") as c:
        roles["server"] = tls.peer_identity(c).role
    t.join()
    assert roles == {"peer": "garbler", "server": "mapowner"}
    with pytest.raises(ValueError):
        tls.add_client(tmp_path, "mapowner")  # a role name is no client name
