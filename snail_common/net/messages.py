"""The message catalogue of the snail protocol and its strict field validation.

Every frame is a msgpack map with ``v`` (protocol version), ``t`` (type) and exactly the
fields below; a missing, unknown or mistyped field is a ProtocolError naming it.
``sid`` is a 16-byte random session id chosen by the client per invocation; labels are
16 bytes each (``snail_common.gc.labels_to_bytes``); long label vectors are cut into chunks
of at most ``LABEL_CHUNK`` labels carrying their ``start`` index and the ``total`` count.

Who sends what (anything else is rejected with ``unexpected`` or ``forbidden``):

connecting side -> server   ``hello``; server replies ``capabilities``
client -> garbler            ``garble_request``, ``error`` (cancels a sid), ``health_request``,
                             ``bye``
client -> evaluator          ``session_start``, ``input_labels``, ``error``, ``health_request``,
                             ``bye``
garbler -> evaluator         ``session_start``, ``tables`` ..., ``tables_end`` (one session
                             at a time per connection); evaluator answers ``done`` or
                             ``error``; an ``error`` {sid} from either side ends that
                             session's stream early, answered by the other side's ``error``
                             {sid} (snail_garbler/streams.py); with ``--table-link``
                             ``aead`` or ``digest`` these go on the table data link,
                             whose token (``link_token``) and key (``link_key``) the
                             evaluator's ``capabilities`` carry (net/datalink.py)
garbler -> client            ``output_zero_labels`` chunks, then ``stats``; or ``error``
evaluator -> client          ``output_labels`` chunks, then ``stats``; or ``error``

Signed digests (gc/attest.py): the garbler's ``capabilities`` carry its Ed25519
``signing_key`` (and ``key_endorsement``, its certificate key's signature over it); the
client names that key to the evaluator (``session_start`` ``signer``); ``tables_end``
{sid, digest, signature} signs the stream just sent, which the evaluator checks against
the bytes it received before it answers, and forwards in its ``stats``
(``tables_digest``, ``block_gates``, ``tables_signature``); the garbler's ``stats`` carry
the same digest and block size and ``outputs_signature`` over its zero-labels.
server -> anyone             ``health`` (reply to ``health_request``), ``error``, ``bye``

The map-owner setting (docs/map-owner.md) adds the role ``mapowner``:
client -> mapowner           ``map_info_request``; answered by ``map_info`` chunks (the
                             sorted public id list and the normalizing transform);
                             ``ot_base_a`` once (answered ``ot_base_b``), then per frame
                             ``ot_ext_u`` (the index bits of its selection), answered by
                             ``sel_table`` chunks carrying the frame handle; per run
                             ``pad_correction_request`` {frame, sid}, answered by
                             ``pad_correction`` {sid, correction}: the frame's pad bits
                             XOR the session's random ones, given once per session
garbler -> mapowner          per session, as it is garbled (ahead of its run)
                             ``map_invocation`` {sid, count, evaluator}; the map owner
                             answers ``ot_base_a`` (once per connection, the garbler
                             replies ``ot_base_b``), ``ot_ext_u`` {sid} with fresh random
                             bits as choices; the garbler sends ``ot_ext_y`` {sid}; the map
                             owner answers ``done`` or ``error``
mapowner -> evaluator        ``owner_labels`` chunks: the labels of the map owner's wires
                             (the last ``count`` input wires of the circuit)
client -> evaluator (relay)  ``relay_open`` {map_owner}, first on a connection of its own
                             (snail_evaluator/relay.py): the evaluator answers
                             ``relay_ready`` once it has a TCP connection to that map owner
                             (one its operator allowed with ``--map-owner``, else
                             ``forbidden`` and no connection), or ``error``; then both
                             ways only ``relay_data`` {data} (at most ``RELAY_DATA`` bytes of
                             the device's end-to-end TLS with the map owner, which the
                             evaluator cannot read), until ``bye`` or a close from either end
``garble_request`` carries the ``map_owner`` address when the
circuit takes map-owner inputs, and names the evaluator replica the client talks to
(``evaluator``: its address as the client reached it, ``evaluator_id``: the ``instance``
of its ``capabilities``); the garbler streams to that replica if its operator's
``--evaluator`` names reach it, else refuses ``forbidden`` (snail_common.net.replicas).
``map_invocation`` names the same replica to the map owner.
``ahead`` (``garble_request``, ``session_start``) marks a reservation: a session garbled
before its client needs it, which yields its place to a live one (snail_common.net.slots).

The garbler never receives input labels and the evaluator never receives a seed or delta:
there is no message carrying them to the wrong role. The map owner never receives a 2D
point, a map id, a pose, a seed or delta; the client never receives a 3D point in the
clear nor a label of the map owner's wires.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from typing import Any

from snail_common.gc.attest import DIGEST_BYTES, PUBLIC_KEY_BYTES, SIGNATURE_BYTES
from snail_common.gc.engine import ENGINES
from snail_common.gc.stream import SCHEMES

from .errors import MALFORMED, MISSING_FIELD, UNKNOWN_FIELD, UNKNOWN_TYPE, ProtocolError

ROLES = ("client", "garbler", "evaluator", "mapowner")
TABLE_LINKS = ("tls", "aead", "digest")  # how the tables travel (datalink.py)
SID_BYTES = 16
LABEL_BYTES = 16
LABEL_CHUNK = 1 << 16  # labels per chunk: 1 MiB
MAX_TEXT = 1024
MAX_LABELS = 1 << 28
DATA_CHUNK = 2 << 20  # bytes of a chunked blob (sel_table, map_info ids) per message
MAX_OT_BYTES = 3 << 20  # one OT message body (u or y): 98,304 chosen OTs
MAX_ADDRESS = 300  # HOST:PORT
RELAY_DATA = 256 << 10  # bytes of the relayed TLS stream per relay_data frame
POINT_BYTES = 32  # an Ed25519 point (ot/group.py)
MAX_ENDORSEMENT = 80  # a DER ECDSA P-256 signature: at most 72 bytes
BASE_OTS = 128
_HASH = re.compile(r"^[0-9a-f]{64}$")

Validator = Callable[[str, Any], None]


def _fail(name: str, what: str, value: Any) -> None:
    raise ProtocolError(MALFORMED, f"field {name!r} must be {what}, got {_show(value)}")


def _show(value: Any) -> str:
    if isinstance(value, (bytes, bytearray, memoryview)):
        return f"{len(value)} bytes"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def text(max_len: int = MAX_TEXT) -> Validator:
    def check(name: str, v: Any) -> None:
        if not isinstance(v, str) or len(v) > max_len:
            _fail(name, f"a string of at most {max_len} characters", v)
    return check


def flag(name: str, v: Any) -> None:
    if type(v) is not bool:
        _fail(name, "true or false", v)


def count(name: str, v: Any) -> None:
    if type(v) is not int or not 0 <= v < 1 << 62:
        _fail(name, "a non-negative integer", v)


def blob(size: int | None = None, multiple: int = 1,
         max_size: int | None = None) -> Validator:
    """Binary: bytes, or a flat byte memoryview (table data sent or received uncopied)."""
    def check(name: str, v: Any) -> None:
        if not isinstance(v, bytes) and not (
                isinstance(v, memoryview) and v.format == "B" and v.ndim == 1 and v.contiguous):
            _fail(name, "binary", v)
        if size is not None and len(v) != size:
            _fail(name, f"{size} bytes", v)
        if max_size is not None and len(v) > max_size:
            _fail(name, f"at most {max_size} bytes", v)
        if len(v) % multiple:
            _fail(name, f"a multiple of {multiple} bytes", v)
    return check


def one_of(choices: tuple[str, ...]) -> Validator:
    def check(name: str, v: Any) -> None:
        if v not in choices:
            _fail(name, f"one of {choices}", v)
    return check


def content_hash(name: str, v: Any) -> None:
    if not isinstance(v, str) or not _HASH.match(v):
        _fail(name, "a SHA-256 hex digest", v)


def seconds(name: str, v: Any) -> None:
    if not isinstance(v, float) or not math.isfinite(v) or v < 0:
        _fail(name, "a non-negative float", v)


def text_list(name: str, v: Any) -> None:
    if not isinstance(v, list) or len(v) > 64 or not all(
            isinstance(x, str) and len(x) <= 64 for x in v):
        _fail(name, "a list of at most 64 short strings", v)


def number_map(kind: type) -> Validator:
    def check(name: str, v: Any) -> None:
        ok = isinstance(v, dict) and len(v) <= 32 and all(
            isinstance(k, str) and len(k) <= 64 and isinstance(x, (int, float))
            and not isinstance(x, bool) and math.isfinite(x) and x >= 0 for k, x in v.items())
        if not ok or (kind is int and not all(type(x) is int for x in v.values())):
            _fail(name, f"a map of names to non-negative {kind.__name__}s", v)
    return check


sid = blob(SID_BYTES)
labels = blob(multiple=LABEL_BYTES)
key16 = blob(16)
circuit = text(128)
scheme = one_of(tuple(SCHEMES))  # the garbling scheme; absent means half-gates
chunk = blob(max_size=DATA_CHUNK)
digest = blob(DIGEST_BYTES)  # BLAKE3 of a table stream (gc/attest.py)
signature = blob(SIGNATURE_BYTES)  # Ed25519
public_key = blob(PUBLIC_KEY_BYTES)  # the garbler's Ed25519 signing key
endorsement = blob(max_size=MAX_ENDORSEMENT)  # ECDSA P-256 (DER) by its certificate key
ot_body = blob(max_size=MAX_OT_BYTES)

# type -> (required fields, optional fields)
SCHEMA: dict[str, tuple[dict[str, Validator], dict[str, Validator]]] = {
    "hello": ({"role": one_of(ROLES), "software": text(64), "max_frame": count}, {}),
    "capabilities": ({"role": one_of(ROLES), "software": text(64), "max_frame": count,
                      "families": text_list, "max_sessions": count},
                     {"max_and_gates": count, "instance": text(64),
                      "signing_key": public_key, "key_endorsement": endorsement,
                      "table_link": one_of(TABLE_LINKS), "link_token": blob(32),
                      "link_key": blob(32)}),
    "session_start": ({"sid": sid, "circuit": circuit, "hash": content_hash},
                      {"scheme": scheme, "ahead": flag, "signer": public_key}),
    "garble_request": ({"sid": sid, "circuit": circuit, "hash": content_hash, "seed": key16,
                        "delta": key16, "key": key16},
                       {"scheme": scheme, "ahead": flag,
                        "map_owner": text(MAX_ADDRESS),
                        "evaluator": text(MAX_ADDRESS), "evaluator_id": text(64)}),
    "input_labels": ({"sid": sid, "start": count, "total": count, "labels": labels}, {}),
    "tables": ({"sid": sid, "data": blob()}, {}),
    "tables_end": ({"sid": sid, "digest": digest, "signature": signature}, {}),
    "done": ({"sid": sid}, {}),
    "output_labels": ({"sid": sid, "start": count, "total": count, "labels": labels}, {}),
    "output_zero_labels": ({"sid": sid, "start": count, "total": count, "labels": labels},
                           {}),
    "stats": ({"sid": sid, "traffic": number_map(int), "timing": number_map(float)},
              {"tables_digest": digest, "block_gates": count, "tables_signature": signature,
               "outputs_signature": signature}),
    "health_request": ({}, {}),
    "health": ({"role": one_of(ROLES), "sessions": number_map(int), "uptime_s": seconds},
               {"engine": one_of(ENGINES), "engine_reason": text(), "engine_threads": count,
                "failpoints": text_list, "signing_key": text(2 * PUBLIC_KEY_BYTES),
                "table_link": one_of(TABLE_LINKS)}),
    "error": ({"code": text(64), "message": text()}, {"sid": sid}),
    "bye": ({}, {}),
    # the map-owner setting
    "map_info_request": ({}, {}),
    "map_info": ({"points": count, "transform": blob(32), "start": count,
                  "ids": blob(multiple=4, max_size=DATA_CHUNK)}, {}),
    "ot_base_a": ({"a": blob(POINT_BYTES)}, {}),
    "ot_base_b": ({"b": blob(BASE_OTS * POINT_BYTES)}, {}),
    "ot_ext_u": ({"start": count, "m": count, "u": ot_body}, {"sid": sid}),
    "ot_ext_y": ({"start": count, "y": ot_body}, {"sid": sid}),
    "sel_table": ({"frame": key16, "start": count, "key": key16, "offset": count,
                   "total": count, "table": chunk}, {}),
    "map_invocation": ({"sid": sid, "count": count, "evaluator": text(MAX_ADDRESS)},
                       {"evaluator_id": text(64)}),
    "pad_correction_request": ({"frame": key16, "sid": sid}, {}),
    "pad_correction": ({"sid": sid, "correction": blob(max_size=MAX_OT_BYTES)}, {}),
    "owner_labels": ({"sid": sid, "start": count, "total": count, "labels": labels}, {}),
    # the relay: a device reaches its map owner through the evaluator
    "relay_open": ({"map_owner": text(MAX_ADDRESS)}, {}),
    "relay_ready": ({}, {}),
    "relay_data": ({"data": blob(max_size=RELAY_DATA)}, {}),
}


def validate(msg: Mapping[str, Any]) -> None:
    """Raise ProtocolError unless ``msg`` (without ``v``) is a well-formed message."""
    kind = msg.get("t")
    if not isinstance(kind, str):
        raise ProtocolError(MISSING_FIELD if kind is None else MALFORMED,
                            "message has no string field 't' (its type)")
    if kind not in SCHEMA:
        raise ProtocolError(UNKNOWN_TYPE, f"unknown message type {_show(kind)}")
    required, optional = SCHEMA[kind]
    for name, check in required.items():
        if name not in msg:
            raise ProtocolError(MISSING_FIELD, f"{kind} message lacks field {name!r}")
        check(name, msg[name])
    for name, value in msg.items():
        if name in required or name == "t":
            continue
        if name not in optional:
            raise ProtocolError(UNKNOWN_FIELD, f"{kind} message has unknown field "
                                               f"{_show(name)}")
        optional[name](name, value)


def make(kind: str, **fields: Any) -> dict[str, Any]:
    """A validated message dict (raises ProtocolError on a programming error as well)."""
    msg = {"t": kind, **fields}
    validate(msg)
    return msg


def error(code: str, message: str, sid_: bytes | None = None) -> dict[str, Any]:
    """An ``error`` message; the text is cut to the protocol's limit."""
    msg = {"t": "error", "code": code, "message": message[:MAX_TEXT]}
    if sid_ is not None:
        msg["sid"] = sid_
    return msg
