"""The ``loc`` circuit family: localization circuits by id (``loc/lm-sil-ldlt-n6``)."""

from __future__ import annotations

from collections.abc import Callable

from snail_common.circuit import registry
from snail_common.circuit.ir import Circuit

from .spec import ID_PATTERN, Spec, build

# Bump on any change to what a localization circuit computes or how it is built (its
# gates, their order, its interface). tests/test_circuit_keys.py fails until you do.
VERSION = "13"


def _resolve(rest: str) -> Callable[[], Circuit]:
    if not ID_PATTERN.match(rest):
        raise registry.UnknownCircuit("malformed localization circuit id")
    spec = Spec.parse(rest)  # ValueError names the bad parameter
    return lambda: build(spec)


FAMILY = registry.Family("loc", VERSION, _resolve, "loc/lm-sil-ldlt-n6")
