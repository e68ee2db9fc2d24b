"""The fewest garbled-table bytes a result's sessions can have streamed: with
``--scheme auto`` each session's scheme is picked from the measured link and engine, so
the floor is per session (three-halves sends 24 bytes per AND gate, half-gates 32)."""

from __future__ import annotations

from snail_common.gc.stream import SCHEMES
from snail_common.net.linkrates import bytes_per_and


def per_and(scheme: str) -> float:
    """Table bytes per AND gate in ``scheme``'s stream."""
    return bytes_per_and(SCHEMES[scheme])


def table_floor(record: dict) -> float:
    """Table bytes at least, for a snail-result/1 record of a garbled localization."""
    schemes = record.get("schemes") or {record["scheme"]: record["invocations"]}
    assert sum(schemes.values()) == record["invocations"], record
    return sum(per_and(name) * count for name, count in schemes.items()) \
        * record["circuit"]["and"]
