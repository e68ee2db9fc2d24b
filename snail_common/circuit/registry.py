"""Circuits by public id: the names client, garbler and evaluator agree on before a run.

An id is ``<family>/<rest>``. The compiler knows no family: each one (float ops,
localization circuits) registers a ``Family`` that turns the rest of an id into a
builder, and a version that it bumps whenever what it builds changes (the cache key;
``tests/test_circuit_keys.py`` holds the families to that). Whatever imports the
families (the roles, the benchmarks) registers them with ``register``.

Ids are parsed strictly (bounded parameters) because servers compile whatever a client
names. Compiled circuits come from the on-disk cache and stay in an in-process LRU bounded
in bytes (``configure``; the most recent circuit always stays), so a daemon compiles each
circuit once; concurrent requests for one id build it once. Clients
ask for ``interface`` only and never hold a netlist or schedule.
"""

from __future__ import annotations

import functools
import re
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from . import cache
from .builder import CircuitTooLarge, and_gate_limit
from .ir import Circuit, Interface
from .schedule import Schedule

MAX_ID_LENGTH = 128
DEFAULT_MEMORY_BYTES = 8 << 30

_ID = re.compile(r"^(?P<family>[a-z]+)/(?P<rest>[A-Za-z0-9_.-]+)$")
_VERSION = re.compile(r"^[A-Za-z0-9_.]+$")

__all__ = ["CircuitTooLarge", "Family", "UnknownCircuit", "check_id", "compiled", "families",
           "interface", "lookup", "register"]


class UnknownCircuit(ValueError):
    """The id names no circuit this build can compile."""


@dataclass(frozen=True)
class Family:
    """A kind of circuit the registry can build.

    ``resolve(rest)`` returns the builder of the circuit ``<name>/<rest>``, or raises
    UnknownCircuit (or ValueError) naming what is wrong with ``rest``. ``version`` goes
    into the cache key: change it whenever a circuit of the family changes."""

    name: str
    version: str
    resolve: Callable[[str], Callable[[], Circuit]]
    example: str  # a valid id, for error messages

    def __post_init__(self) -> None:
        if not re.fullmatch(r"[a-z]+", self.name):
            raise ValueError(f"family name {self.name!r} must be lower-case letters")
        if not _VERSION.match(self.version):
            raise ValueError(f"family version {self.version!r} must match {_VERSION.pattern}")


_families: dict[str, Family] = {}
_lru: OrderedDict[str, tuple[Circuit, Schedule]] = OrderedDict()
_memory = {"max_bytes": DEFAULT_MEMORY_BYTES}
_lru_lock = threading.Lock()
_build_locks: dict[str, threading.Lock] = {}


def register(family: Family) -> None:
    """Make ``family`` servable (registering the same family again is a no-op)."""
    known = _families.get(family.name)
    if known is not None and known != family:
        raise ValueError(f"circuit family {family.name!r} is already registered")
    _families[family.name] = family


def configure(memory_bytes: int | None = None) -> None:
    """Bound the bytes of compiled circuits kept in this process."""
    _memory["max_bytes"] = DEFAULT_MEMORY_BYTES if memory_bytes is None else memory_bytes
    with _lru_lock:
        _trim()


def _trim() -> None:
    """Drop the least recently used circuits beyond the bound (caller holds the lock)."""
    while len(_lru) > 1 and sum(map(footprint, _lru.values())) > _memory["max_bytes"]:
        _lru.popitem(last=False)


def footprint(hit: tuple[Circuit, Schedule]) -> int:
    """Bytes of the arrays of a compiled circuit and its schedule (resident or mapped)."""
    return sum(value.nbytes for part in hit for value in vars(part).values()
               if isinstance(value, np.ndarray))


def families() -> tuple[str, ...]:
    """Names of the registered families, in registration order."""
    return tuple(_families)


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
                _trim()
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


def interface(circuit_id: str, max_and: int | None = None) -> Interface:
    """The client's view of ``circuit_id`` (layout, content hash, size): from a compiled
    circuit already in memory, else from the cache's sidecar, else built unscheduled.
    With ``max_and``, a circuit of more AND gates raises CircuitTooLarge, and a build
    stops as soon as it crosses the limit (a client asks for no circuit its servers
    would refuse, and builds none of it beyond their limit)."""
    iface = _interface(circuit_id, max_and)
    if max_and is not None and iface.counts["and"] > max_and:
        raise CircuitTooLarge(f"{circuit_id} has {iface.counts['and']:,} AND gates, more "
                              f"than {max_and:,}")
    return iface


@functools.lru_cache(maxsize=64)
def _interface(circuit_id: str, max_and: int | None) -> Interface:
    name, build = _resolve(circuit_id)
    hit = lookup(circuit_id)
    if hit is not None:
        return hit[0].interface()
    try:
        with and_gate_limit(max_and):
            return cache.cached_interface(name, build)
    except CircuitTooLarge as exc:
        raise CircuitTooLarge(f"{circuit_id}: {exc}") from None


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
    known = ", ".join(_families) or "none registered"
    m = _ID.match(circuit_id)
    if not m:
        raise UnknownCircuit(f"malformed circuit id {circuit_id!r} (expected "
                             f"'<family>/<name>' with family one of: {known})")
    family = _families.get(m["family"])
    if family is None:
        raise UnknownCircuit(f"unknown circuit family {m['family']!r} in {circuit_id!r} "
                             f"(known: {known})")
    try:
        build = family.resolve(m["rest"])
    except ValueError as exc:  # UnknownCircuit included
        raise UnknownCircuit(f"{circuit_id!r}: {exc} (e.g. {family.example!r})") from None
    return f"{family.name}-{m['rest']}.{family.version}", build
