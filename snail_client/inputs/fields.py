"""Checked access to decoded JSON fields: every error names the field's path first, so the
command line can print one line that says what to fix (exit 2)."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from snail_common.loc.problem import ProblemError, parse_json

T = TypeVar("T")


class InputError(ProblemError):
    """An input file (camera, tag map, image, COLMAP model) that cannot be used as given."""


def load(path: str | Path, parse: Callable[[Any], T]) -> T:
    """``parse`` of a JSON file's content, its errors prefixed with the file name."""
    try:
        return parse(read_json(path))
    except InputError as exc:
        text = str(exc)
        if text.startswith(f"{path}:"):
            raise
        raise InputError(f"{path}: {text}") from None


def read_json(path: str | Path) -> Any:
    """A JSON file's content; InputError naming the file when it cannot be read."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read ({exc.__class__.__name__})") from None
    try:
        return parse_json(text)
    except ProblemError as exc:
        raise InputError(f"{path}: {exc}") from None


def obj(value: Any, where: str) -> dict:
    if not isinstance(value, dict):
        raise InputError(f"{where}: expected an object, got {type(value).__name__}")
    return value


def field(o: dict, key: str, where: str = "") -> Any:
    if key not in o:
        raise InputError(f"{where}{key}: missing")
    return o[key]


def number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{where}: not a number ({json.dumps(value)[:40]})")
    if not math.isfinite(value):
        raise InputError(f"{where}: not a finite number")
    return float(value)


def positive(value: Any, where: str) -> float:
    x = number(value, where)
    if x <= 0:
        raise InputError(f"{where}: must be positive, got {x:g}")
    return x


def integer(value: Any, where: str, low: int = 0) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise InputError(f"{where}: expected an integer >= {low}, got {json.dumps(value)[:40]}")
    return value


def numbers(value: Any, count: int, where: str) -> np.ndarray:
    if not isinstance(value, list) or len(value) != count:
        got = f"{len(value)}" if isinstance(value, list) else type(value).__name__
        raise InputError(f"{where}: expected {count} numbers, got {got}")
    return np.array([number(v, f"{where}[{i}]") for i, v in enumerate(value)])


def check_format(o: dict, expected: str) -> None:
    fmt = o.get("format")
    if fmt != expected:
        raise InputError(f"format: expected {expected!r}, got {fmt!r}")
