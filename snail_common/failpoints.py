"""Failpoints: the ways a server can misbehave, as named points a daemon can switch on.

Tests and deployments must exercise the real daemons cheating (issue 44: a client audits
the garbler, a failing run is attributed). As in fail-rs or gofail, each fault is a named
point in the code, a one-line call site ``if failpoints.fire("garbler.zero_label"):``, and
a no-op unless the process was started with the environment variable

    SNAIL_FAILPOINTS="name=when;name=when"

where ``when`` is ``always``, ``1/N`` (the N-th, 2N-th ... time the point is reached) or
``run:K`` (the K-th time only; counting from 1). Only a daemon's start reads it
(``configure``): no flag, message or later change of the environment switches a point on.
A daemon arms the points of its own role; a name of another role's is accepted (one
setting may serve a whole compose file) and left unarmed; an unknown name or a malformed
``when`` is an error naming the setting (the daemons exit 2). A daemon with armed points
says so in a warning line at start and in ``/health`` (``armed``).

This module is the whole registry, on the lowest floor so that any layer may hold a call
site; what each point does lives at its call site.
"""

from __future__ import annotations

import os
import re
import threading
from collections.abc import Mapping
from dataclasses import dataclass

ENV = "SNAIL_FAILPOINTS"
# name -> what firing it does (the call sites implement it; docs/formats.md lists them)
NAMES: dict[str, str] = {
    "garbler.table_bit": "flip one bit in each of the first table words of the stream",
    "garbler.zero_label": "send L0 ^ D for one output wire",
    "garbler.and_as_or": "garble one AND gate as OR",
    "garbler.stale_circuit": "garble another circuit of the same size",
    "evaluator.output_label": "return a wrong output label",
    "evaluator.digest": "forward a wrong signed digest",
}
_WHEN = re.compile(r"^(?:(always)|1/([1-9][0-9]{0,8})|run:([1-9][0-9]{0,8}))$")


class FailpointError(ValueError):
    """$SNAIL_FAILPOINTS cannot be read; the message names the setting and the entry."""


@dataclass
class _Point:
    when: str
    every: int  # fires when the count is a multiple of this (1: always) ...
    only: int  # ... or exactly this count (0: no such rule)
    hits: int = 0

    def hit(self) -> bool:
        self.hits += 1
        return self.hits == self.only if self.only else self.hits % self.every == 0


_lock = threading.Lock()
_armed: dict[str, _Point] = {}


def parse(text: str) -> dict[str, str]:
    """{name: when} of a $SNAIL_FAILPOINTS value; FailpointError on anything else."""
    points: dict[str, str] = {}
    for entry in (e.strip() for e in text.split(";")):
        if not entry:
            continue
        name, eq, when = (part.strip() for part in entry.partition("="))
        if name not in NAMES:
            raise FailpointError(f"${ENV}: unknown failpoint {name!r} (known: "
                                 f"{', '.join(NAMES)})")
        if not eq or not _WHEN.match(when):
            raise FailpointError(f"${ENV}: {entry!r}: expected {name}=always, "
                                 f"{name}=1/N or {name}=run:K")
        if name in points:
            raise FailpointError(f"${ENV}: {name} is set twice")
        points[name] = when
    return points


def configure(role: str, environ: Mapping[str, str] | None = None) -> list[str]:
    """Arm ``role``'s points named in $SNAIL_FAILPOINTS (at a daemon's start, once);
    returns the armed ``name=when`` entries (none: every point stays a no-op)."""
    points = parse((os.environ if environ is None else environ).get(ENV, ""))
    with _lock:
        _armed.clear()
        for name, when in points.items():
            if name.split(".")[0] != role:
                continue
            match = _WHEN.match(when)
            every = 1 if match[1] else int(match[2] or 1)
            _armed[name] = _Point(when, every, int(match[3] or 0))
    return armed()


def armed() -> list[str]:
    """The armed points as ``name=when``, for the start-up warning and ``/health``."""
    with _lock:
        return [f"{name}={p.when}" for name, p in _armed.items()]


def fire(name: str) -> bool:
    """Count one pass through point ``name``; whether its fault happens this time.
    False at once when nothing is armed (the production path)."""
    if not _armed:
        return False
    if name not in NAMES:
        raise KeyError(f"no failpoint {name!r}")
    with _lock:
        point = _armed.get(name)
        return point is not None and point.hit()
