"""Memoize per object identity for as long as the object lives.

Executors derive run plans from a Schedule (unhashable, large): the plan is built on first
use and dropped when the schedule is garbage collected.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def per_object(build: Callable[[T], R]) -> Callable[[T], R]:
    """``build(obj)``, computed once per live ``obj`` (keyed by identity)."""
    cache: dict[int, R] = {}

    def get(obj: T) -> R:
        key = id(obj)
        value = cache.get(key)
        if value is None:
            value = cache[key] = build(obj)
            weakref.finalize(obj, cache.pop, key, None)
        return value

    get.__doc__ = build.__doc__
    return get
