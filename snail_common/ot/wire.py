"""Strict checks of OT messages (msgpack-able dicts with a type ``t`` and byte fields).

A message with a missing, unknown or mistyped field, a blob of the wrong length or a count
out of bounds raises a ProtocolError whose text names the field, so the daemons can answer
it with an ``error`` message as for every other frame.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..net.errors import (
    BAD_REQUEST,
    MALFORMED,
    MISSING_FIELD,
    UNEXPECTED,
    UNKNOWN_FIELD,
    ProtocolError,
)


def fields(msg: Any, kind: str, names: tuple[str, ...]) -> Mapping[str, Any]:
    """``msg`` if it is a dict of type ``kind`` with exactly the fields ``names`` (and ``t``)."""
    if not isinstance(msg, Mapping):
        raise ProtocolError(MALFORMED, f"an OT message must be a map, got {type(msg).__name__}")
    got = msg.get("t")
    if got != kind:
        raise ProtocolError(UNEXPECTED, f"field 't': expected {kind!r} here, got {_show(got)}")
    for name in names:
        if name not in msg:
            raise ProtocolError(MISSING_FIELD, f"field {name!r} missing in {kind!r}")
    extra = sorted(str(k) for k in msg if k not in names and k != "t")
    if extra:
        raise ProtocolError(UNKNOWN_FIELD, f"field {extra[0]!r} unknown in {kind!r}")
    return msg


def blob(msg: Mapping[str, Any], name: str, size: int) -> bytes:
    """The bytes field ``name``, exactly ``size`` long."""
    value = msg[name]
    if not isinstance(value, (bytes, bytearray)):
        raise ProtocolError(MALFORMED, f"field {name!r} must be binary, got {_show(value)}")
    if len(value) != size:
        raise ProtocolError(MALFORMED, f"field {name!r} must be {size} bytes, "
                                       f"got {len(value)}")
    return bytes(value)


def integer(msg: Mapping[str, Any], name: str, low: int, high: int) -> int:
    """The integer field ``name``, within [low, high]."""
    value = msg[name]
    if type(value) is not int:
        raise ProtocolError(MALFORMED, f"field {name!r} must be an integer, got {_show(value)}")
    if not low <= value <= high:
        raise ProtocolError(BAD_REQUEST, f"field {name!r} must be in [{low}, {high}], "
                                         f"got {value}")
    return value


def _show(value: Any) -> str:
    if isinstance(value, (bytes, bytearray)):
        return f"{len(value)} bytes"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
