"""Circuits by public id: the names client, garbler and evaluator agree on before a run.

An id is ``<family>/<rest>``:
- ``ops/<op>-x<count>``: ``count`` independent float32 operations (a benchmark and test
  family), inputs ``x`` and ``y`` of shape (count,) (``x`` only for ``fsqrt``), output ``z``;
- ``loc/<rest>``: a localization circuit of ``snail_common.loc.circuits``.

Ids are parsed strictly (bounded parameters) because servers compile whatever a client
names. Compiled circuits come from the on-disk cache and stay in a small in-process LRU, so
a daemon compiles each circuit once; concurrent requests for one id build it once. Clients
ask for ``interface`` only and never hold a netlist or schedule.
"""

from __future__ import annotations

import functools
import re
import threading
from collections import OrderedDict
from collections.abc import Callable

from snail_common.arith import fcmp
from snail_common.arith.fadd import fadd, fsub
from snail_common.arith.fdiv import fdiv
from snail_common.arith.fmul import fmul
from snail_common.arith.fsqrt import fsqrt

from . import cache
from .builder import CircuitBuilder, CircuitTooLarge, and_gate_limit
from .ir import Circuit, Interface
from .schedule import Schedule

MAX_OPS = 4096
MAX_ID_LENGTH = 128
LRU_SIZE = 4

_ID = re.compile(r"^(?P<family>[a-z]+)/(?P<rest>[A-Za-z0-9_.-]+)$")
_OPS = re.compile(r"^(?P<op>[a-z]+)-x(?P<count>[1-9][0-9]{0,3})$")

# op name -> (function of (builder, x, y) or (builder, x), arity, output dtype)
OPS: dict[str, tuple[Callable, int, str]] = {
    "fadd": (fadd, 2, "float32"),
    "fsub": (fsub, 2, "float32"),
    "fmul": (fmul, 2, "float32"),
    "fdiv": (fdiv, 2, "float32"),
    "fsqrt": (fsqrt, 1, "float32"),
    "fmin": (fcmp.fmin, 2, "float32"),
    "fmax": (fcmp.fmax, 2, "float32"),
    "flt": (fcmp.lt, 2, "bool"),
    "fle": (fcmp.le, 2, "bool"),
    "feq": (fcmp.eq, 2, "bool"),
}

FAMILIES = ("ops", "loc")


class UnknownCircuit(ValueError):
    """The id names no circuit this build can compile."""


_lru: OrderedDict[str, tuple[Circuit, Schedule]] = OrderedDict()
_lru_lock = threading.Lock()
_build_locks: dict[str, threading.Lock] = {}


def compiled(circuit_id: str, max_and: int | None = None) -> tuple[Circuit, Schedule]:
    """The circuit and schedule named ``circuit_id`` (thread-safe, built at most once).
    With ``max_and``, a circuit of more AND gates raises CircuitTooLarge: a build stops
    as soon as it crosses the limit, and nothing is cached."""
    name, build = _resolve(circuit_id)
    with _lru_lock:
        hit = _lru.get(circuit_id)
        if hit is not None:
            _lru.move_to_end(circuit_id)
            return _within(circuit_id, hit, max_and)
        lock = _build_locks.setdefault(circuit_id, threading.Lock())
    try:
        with lock:  # one builder per id; others wait for it and then hit the LRU
            with _lru_lock:
                hit = _lru.get(circuit_id)
            if hit is not None:
                return _within(circuit_id, hit, max_and)
            try:
                with and_gate_limit(max_and):
                    built = cache.cached(name, build)
            except CircuitTooLarge as exc:
                raise CircuitTooLarge(f"{circuit_id}: {exc}") from None
            hit = _within(circuit_id, built, max_and)  # a refused circuit stays out
            with _lru_lock:
                _lru[circuit_id] = hit
                while len(_lru) > LRU_SIZE:
                    _lru.popitem(last=False)
            return hit
    finally:  # also after a refusal or a failed build: ids come from requests
        with _lru_lock:
            _build_locks.pop(circuit_id, None)


def _within(circuit_id: str, hit: tuple[Circuit, Schedule],
            max_and: int | None) -> tuple[Circuit, Schedule]:
    """``hit``, unless it has more than ``max_and`` AND gates (one compiled elsewhere
    with a higher limit, found in the cache)."""
    n_and = hit[1].n_and
    if max_and is not None and n_and > max_and:
        raise CircuitTooLarge(f"{circuit_id} has {n_and:,} AND gates, more than "
                              f"{max_and:,}")
    return hit


@functools.lru_cache(maxsize=64)
def interface(circuit_id: str) -> Interface:
    """The client's view of ``circuit_id`` (layout, content hash, size): from a compiled
    circuit already in memory, else from the cache's sidecar, else built unscheduled."""
    name, build = _resolve(circuit_id)
    hit = lookup(circuit_id)
    return hit[0].interface() if hit is not None else cache.cached_interface(name, build)


def lookup(circuit_id: str) -> tuple[Circuit, Schedule] | None:
    """The compiled circuit if it is in the in-process LRU, else None (never builds)."""
    with _lru_lock:
        return _lru.get(circuit_id)


def check_id(circuit_id: str) -> None:
    """Raise UnknownCircuit unless ``circuit_id`` is well formed (without compiling it)."""
    _resolve(circuit_id)


def _resolve(circuit_id: str) -> tuple[str, Callable[[], Circuit]]:
    """(cache name, builder) of an id; raises UnknownCircuit naming what is wrong."""
    if not isinstance(circuit_id, str) or len(circuit_id) > MAX_ID_LENGTH:
        raise UnknownCircuit(f"circuit id must be a string of at most {MAX_ID_LENGTH} "
                             f"characters, got {circuit_id!r:.80}")
    m = _ID.match(circuit_id)
    if not m:
        raise UnknownCircuit(f"malformed circuit id {circuit_id!r} (expected "
                             f"'<family>/<name>' with family one of {FAMILIES})")
    family, rest = m["family"], m["rest"]
    if family == "ops":
        return _ops(circuit_id, rest)
    if family == "loc":
        return _loc(circuit_id, rest)
    raise UnknownCircuit(f"unknown circuit family {family!r} in {circuit_id!r} "
                         f"(known: {', '.join(FAMILIES)})")


def _ops(circuit_id: str, rest: str) -> tuple[str, Callable[[], Circuit]]:
    m = _OPS.match(rest)
    if not m:
        raise UnknownCircuit(f"malformed ops circuit id {circuit_id!r} "
                             f"(expected e.g. 'ops/fmul-x64')")
    op, count = m["op"], int(m["count"])
    if op not in OPS:
        raise UnknownCircuit(f"unknown op {op!r} in {circuit_id!r} (known: {', '.join(OPS)})")
    if count > MAX_OPS:
        raise UnknownCircuit(f"op count {count} in {circuit_id!r} exceeds {MAX_OPS}")
    return f"ops-{op}-x{count}", lambda: build_ops(op, count)


def build_ops(op: str, count: int) -> Circuit:
    """``count`` independent float32 ``op``s: z[i] = op(x[i], y[i])."""
    fn, arity, out_dtype = OPS[op]
    b = CircuitBuilder()
    args = [b.input(name, (count,), bits=32, dtype="float32") for name in "xy"[:arity]]
    z = fn(b, *args)
    b.output("z", z[..., None] if out_dtype == "bool" else z, dtype=out_dtype)
    return b.build()


def _loc(circuit_id: str, rest: str) -> tuple[str, Callable[[], Circuit]]:
    from snail_common.loc import circuits as loc  # heavy and optional: only for loc ids

    if not loc.ID_PATTERN.match(rest):
        raise UnknownCircuit(f"malformed localization circuit id {circuit_id!r} "
                             f"(expected e.g. 'loc/lm-sil-ldlt-n6')")
    try:
        spec = loc.Spec.parse(rest)
    except ValueError as e:
        raise UnknownCircuit(f"{circuit_id!r}: {e}") from None
    return spec.cache_name, lambda: loc.build(spec)
