"""Which engine garbles and evaluates: the native kernel (native/) or numpy, the reference.

``SNAIL_ENGINE`` (or a caller's ``engine=``) is ``native``, ``numpy`` or ``auto`` (the
default: native where it can run, else numpy). Both engines produce the same tables,
labels and outputs bit for bit (tests/test_gc_native.py), so a garbler on one engine
serves an evaluator on the other. Asking for ``native`` where it cannot run is an error;
``auto`` falls back to numpy and ``engine_status`` says so and why, for the daemons'
start-up line and ``/health``.
"""

from __future__ import annotations

import os

from .native.build import NativeUnavailable, library
from .native.run import kernel_threads

ENGINE_ENV = "SNAIL_ENGINE"
ENGINES = ("native", "numpy")
CHOICES = ("auto", *ENGINES)


def requested(engine: str | None = None) -> str:
    """The engine asked for: ``engine``, else $SNAIL_ENGINE, else auto."""
    choice = engine or os.environ.get(ENGINE_ENV) or "auto"
    if choice not in CHOICES:
        source = "engine" if engine else ENGINE_ENV
        raise ValueError(f"{source} must be one of {', '.join(CHOICES)}, got {choice!r}")
    return choice


def resolve(engine: str | None = None) -> str:
    """The engine that will run: "native" or "numpy". NativeUnavailable when native is
    asked for explicitly and cannot run."""
    choice = requested(engine)
    if choice == "numpy":
        return "numpy"
    try:
        library()
    except NativeUnavailable:
        if choice == "native":
            raise
        return "numpy"
    return "native"


def engine_status(engine: str | None = None) -> dict[str, str]:
    """{"engine": what serves, "requested": what was asked} plus, for a numpy fallback,
    "reason": why the native kernel is not serving, and for native, "threads": how many
    a run's wide steps are cut across ($SNAIL_KERNEL_THREADS; ValueError if bad)."""
    choice = requested(engine)
    status = {"engine": "numpy", "requested": choice}
    if choice == "numpy":
        return status
    try:
        library()
    except NativeUnavailable as exc:
        if choice == "native":
            raise
        status["reason"] = str(exc)
        return status
    status["engine"] = "native"
    status["threads"] = str(kernel_threads())
    return status
