"""What the garbler's failpoints do (snail_common/failpoints.py; docs/formats.md).

Each is a garbler that misbehaves the way a buggy or compromised host would, so that tests
and deployments see the client's audits and attribution work on the real daemon:

- ``garbler.table_bit``: flip the low bit of each of the first 64 ciphertexts of the
  stream's first table frame (the evaluation uses each with probability 1/2, so it uses
  one but with probability 2^-64) and sign what is sent: the output labels come out
  invalid, and the tables differ from the client's;
- ``garbler.zero_label``: send L0 ^ D for one output wire: it decodes to the other bit,
  silently (the wire a malicious garbler would pick: a bit two-thirds up the first
  gradient word where the circuit has one, a bias LM converges on; else output 0);
- ``garbler.and_as_or``: garble the schedule's first AND gate as OR (its input and output
  zero-labels taken as their complements: OR(a, b) = NOT AND(NOT a, NOT b)), the labels
  stay valid, the function is another;
- ``garbler.stale_circuit``: garble another circuit of the same size and wiring, as a stale
  or mismatched build would: the constant-one wire read as zero (every NOT dropped).

Where one fires, the session's garbler (perhaps a lane of a batch) is left after its
header and a garbler of this module streams instead, on the numpy engine where it needs
the AND kernel (both engines make the same stream: gc/engine.py).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from snail_common import failpoints
from snail_common.circuit import registry
from snail_common.circuit.runner import AndKernel
from snail_common.circuit.slots import Rows, gather_into
from snail_common.gc import Garbler, check_delta
from snail_common.gc.stream import HEADER, Header

FLIPPED_CIPHERTEXTS = 64
CIPHERTEXT = 16


class _AndAsOr(Garbler):
    """Garbles AND gate 0 as OR, everything else as asked."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, engine="numpy", **kwargs)

    def _and_kernel(self) -> AndKernel:
        garble, delta = super()._and_kernel(), self._delta

        def kernel(labels: np.ndarray, a: Rows, b: Rows, g0: int, out: np.ndarray,
                   tables: np.ndarray | None) -> None:
            if g0 != 0:
                garble(labels, a, b, g0, out, tables)
                return
            n = len(out)  # gate 0's operands complemented in a private copy of the block's
            ops = np.empty((2 * n, 2), np.uint64)
            gather_into(labels, a, ops[:n])
            gather_into(labels, b, ops[n:])
            ops[0] ^= delta
            ops[n] ^= delta
            garble(ops, slice(0, n, 1), slice(n, 2 * n, 1), g0, out, tables)
            out[0] ^= delta

        return kernel


class _Stale(Garbler):
    """Garbles the circuit with its constant-one wire as zero."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._input_zero[1] ^= self._delta  # slot 1 holds the constant one


CHEATS = {"garbler.and_as_or": _AndAsOr, "garbler.stale_circuit": _Stale}


def frames(garbler: Any, req: dict[str, Any]) -> tuple[Iterator[bytes | memoryview], Any]:
    """The session's stream as this garbler sends it, and the garbler whose output
    zero-labels go with it: ``garbler``'s own, unless a failpoint fires."""
    fired = [name for name in CHEATS if failpoints.fire(name)]  # each point counts
    cheat = CHEATS[fired[0]] if fired else None
    if cheat is None:
        stream = garbler.frames()
    else:
        honest = garbler.frames()
        header = Header.unpack(bytes(next(honest)[: HEADER.size]))
        honest.close()  # a lane leaves its batch
        _, schedule = registry.compiled(req["circuit"])
        garbler = cheat(schedule, req["seed"], req["delta"], req["key"],
                        block_gates=header.block_gates, scheme=header.scheme)
        stream = garbler.frames()
    if failpoints.fire("garbler.table_bit"):
        stream = _flip_table_bits(stream)
    return stream, garbler


def _flip_table_bits(stream: Iterator[bytes | memoryview]) -> Iterator[bytes | memoryview]:
    yield next(stream)  # the header
    first = bytearray(next(stream))
    for pos in range(0, min(len(first), FLIPPED_CIPHERTEXTS * CIPHERTEXT), CIPHERTEXT):
        first[pos] ^= 1
    yield bytes(first)
    yield from stream


def zero_labels(labels: np.ndarray, req: dict[str, Any]) -> np.ndarray:
    """The output zero-labels as this garbler sends them: one complemented where
    ``garbler.zero_label`` fires."""
    if not failpoints.fire("garbler.zero_label"):
        return labels
    labels = np.array(labels, np.uint64)
    labels[_worst_output(req["circuit"])] ^= check_delta(req["delta"])
    return labels


def _worst_output(circuit_id: str) -> int:
    start = 0
    for group in registry.interface(circuit_id).output_groups:
        if group.name == "grad":
            return start + 2 * group.bits // 3
        start += group.size
    return 0
