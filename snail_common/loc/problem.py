"""Problem files (`snail-problem/1`, see shared/FORMATS.md) and sequences of them.

Every check raises ProblemError with the JSON path of the field at fault first, so the
command line can print one line that tells the user what to fix.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .geometry import so3_exp

FORMAT = "snail-problem/1"
MIN_POINTS = 4
DIST_LENGTHS = (4, 5, 8, 12, 14)  # the coefficient counts OpenCV accepts
_BEHIND_SHOWN = 5  # how many offending points a message lists by index


class ProblemError(ValueError):
    """A problem or sequence file that cannot be solved as given; names the field."""


@dataclass(frozen=True)
class PoseVectors:
    """A pose as the files and OpenCV write it: Rodrigues rvec and tvec, world to camera."""

    rvec: np.ndarray  # (3,)
    tvec: np.ndarray  # (3,)


@dataclass(frozen=True)
class Problem:
    K: np.ndarray  # (3, 3) intrinsics
    dist: np.ndarray  # (k,) OpenCV distortion coefficients, zeros(5) when the file has none
    points2d: np.ndarray  # (n, 2) pixels
    points3d: np.ndarray  # (n, 3) world
    initial_pose: PoseVectors | None  # None only for frames after the first of a sequence
    reference_pose: PoseVectors | None = None
    image_size: tuple[int, int] | None = None  # (width, height) when the file gives it

    @property
    def n(self) -> int:
        return len(self.points2d)


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ProblemError(f"{where}: not a number ({json.dumps(value)[:40]})")
    if not math.isfinite(value):
        raise ProblemError(f"{where}: not a finite number")
    return float(value)


def _numbers(value: Any, count: int, where: str) -> np.ndarray:
    if not isinstance(value, list) or len(value) != count:
        got = f"{len(value)}" if isinstance(value, list) else type(value).__name__
        raise ProblemError(f"{where}: expected {count} numbers, got {got}")
    return np.array([_number(v, f"{where}[{i}]") for i, v in enumerate(value)])


def _rows(value: Any, width: int, where: str) -> np.ndarray:
    if not isinstance(value, list):
        raise ProblemError(f"{where}: expected a list of points, got {type(value).__name__}")
    rows = [_numbers(row, width, f"{where}[{i}]") for i, row in enumerate(value)]
    return np.array(rows, dtype=np.float64).reshape(len(rows), width)


def _field(obj: dict, key: str, where: str) -> Any:
    if key not in obj:
        raise ProblemError(f"{where}{key}: missing")
    return obj[key]


def _object(value: Any, where: str) -> dict:
    if not isinstance(value, dict):
        raise ProblemError(f"{where}: expected an object, got {type(value).__name__}")
    return value


def _pose(value: Any, where: str) -> PoseVectors:
    obj = _object(value, where)
    return PoseVectors(rvec=_numbers(_field(obj, "rvec", f"{where}."), 3, f"{where}.rvec"),
                       tvec=_numbers(_field(obj, "tvec", f"{where}."), 3, f"{where}.tvec"))


def parse_camera_block(value: Any, where: str = "camera"
                       ) -> tuple[np.ndarray, np.ndarray, tuple[int, int] | None]:
    """(K, dist, (width, height) or None) of a camera object: a problem's ``camera`` block
    or a ``snail-camera/1`` file (``where`` prefixes the field names in errors)."""
    at = f"{where}." if where else ""
    cam = _object(value, where or "camera")
    f = {k: _number(_field(cam, k, at), f"{at}{k}") for k in ("fx", "fy", "cx", "cy")}
    for k in ("fx", "fy"):
        if f[k] <= 0:
            raise ProblemError(f"{at}{k}: must be positive, got {f[k]}")
    K = np.array([[f["fx"], 0.0, f["cx"]], [0.0, f["fy"], f["cy"]], [0.0, 0.0, 1.0]])
    dist = np.zeros(5)
    if cam.get("dist") is not None:
        raw = cam["dist"]
        if not isinstance(raw, list) or len(raw) not in DIST_LENGTHS:
            raise ProblemError(f"{at}dist: expected {', '.join(map(str, DIST_LENGTHS))} "
                               "numbers (OpenCV's k1, k2, p1, p2[, k3, ...])")
        dist = _numbers(raw, len(raw), f"{at}dist")
    size = None
    if "width" in cam or "height" in cam:
        dims = []
        for k in ("width", "height"):
            v = _field(cam, k, at)
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise ProblemError(f"{at}{k}: expected a positive integer, got {v!r}")
            dims.append(v)
        size = (dims[0], dims[1])
    return K, dist, size


def parse_problem(obj: Any, *, require_initial_pose: bool = True) -> Problem:
    """Validate a decoded `snail-problem/1` object. Sequences pass require_initial_pose=False
    for frames after the first, which then start from the previous frame's result."""
    obj = _object(obj, "problem")
    fmt = obj.get("format")
    if fmt != FORMAT:
        raise ProblemError(f"format: expected {FORMAT!r}, got {fmt!r}")
    K, dist, size = parse_camera_block(_field(obj, "camera", ""))
    p2 = _rows(_field(obj, "points2d", ""), 2, "points2d")
    p3 = _rows(_field(obj, "points3d", ""), 3, "points3d")
    if len(p2) < MIN_POINTS:
        raise ProblemError(f"points2d: need at least {MIN_POINTS} points, got {len(p2)}")
    if len(p2) != len(p3):
        raise ProblemError(f"points2d: {len(p2)} points but points3d has {len(p3)}")
    initial = obj.get("initial_pose")
    if initial is None and require_initial_pose:
        raise ProblemError("initial_pose: missing")
    return Problem(K=K, dist=dist, points2d=p2, points3d=p3,
                   initial_pose=None if initial is None else _pose(initial, "initial_pose"),
                   reference_pose=(None if obj.get("reference_pose") is None
                                   else _pose(obj["reference_pose"], "reference_pose")),
                   image_size=size)


def parse_json(text: str) -> Any:
    """JSON text; ProblemError saying where it is broken (or that it nests deeper than
    the reader's recursion allows, rather than a RecursionError)."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ProblemError(f"invalid JSON at line {exc.lineno} column {exc.colno}: "
                           f"{exc.msg}") from None
    except RecursionError:
        raise ProblemError("invalid JSON: nested too deeply") from None



def _read(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ProblemError(f"{path}: cannot read ({exc})") from None


def load_problem(path: str | Path) -> Problem:
    """One problem file; it must carry an initial pose."""
    return parse_problem(parse_json(_read(Path(path))))


def load_sequence(path: str | Path) -> list[Problem]:
    """A sequence for `track` (see ``read_sequence``), refusing it at its first bad frame."""
    frames = []
    for _, frame in read_sequence(path):
        if isinstance(frame, ProblemError):
            raise frame
        frames.append(frame)
    return frames


def read_sequence(path: str | Path, parse: Callable[..., Any] | None = None
                  ) -> list[tuple[str, Any]]:
    """The frames of a sequence for `track`, each named (``line 3``, a file name,
    ``[2]``) and parsed on its own, so one bad frame is reported (as its ProblemError) and
    the others still run: a folder of .json problem files in name order, a JSON array of
    problems, one (pretty-printed) problem, or JSON Lines (blank lines skipped). Only the
    first frame needs an initial pose. ``parse`` (default ``parse_problem``) takes a
    decoded object and ``require_initial_pose``: ``mapfile.parse_frame`` reads a sequence
    of snail-frame/1. ProblemError for a sequence that cannot be read at all."""
    parse = parse or parse_problem
    path = Path(path)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix == ".json" and p.is_file())
        texts = [(p.name, _read(p)) for p in files]
        items = [(name, _parse_named(name, text, i == 0, parse)) for i, (name, text)
                 in enumerate(texts)]
    else:
        text = _read(path)
        try:
            whole = json.loads(text)
        except (json.JSONDecodeError, RecursionError):
            whole = None  # JSON Lines, or broken: read line by line
        if isinstance(whole, list):
            items = [(f"[{i}]", _parse_named(f"[{i}]", obj, i == 0, parse, parsed=True))
                     for i, obj in enumerate(whole)]
        elif isinstance(whole, dict):  # one problem: on one line (JSON Lines) or several
            name = "line 1" if "\n" not in text.strip() else "problem"
            items = [(name, _parse_named(name, whole, True, parse, parsed=True))]
        else:
            lines = [(no, line) for no, line in enumerate(text.splitlines(), 1)
                     if line.strip()]
            items = [(f"line {no}", _parse_named(f"line {no}", line, i == 0, parse))
                     for i, (no, line) in enumerate(lines)]
    if not items:
        raise ProblemError(f"{path}: no problems in the sequence")
    return items


def _parse_named(where: str, source: Any, first: bool, parse: Callable[..., Any],
                 parsed: bool = False) -> Any:
    try:
        obj = source if parsed else parse_json(source)
        return parse(obj, require_initial_pose=first)
    except ProblemError as exc:
        return ProblemError(f"{where}: {exc}")


def check_in_front(problem: Problem, pose: PoseVectors | None = None) -> None:
    """Every map point must be in front of the camera (camera z > 0) at the starting pose
    (the initial pose unless one is given), or the projection is meaningless."""
    pose = pose if pose is not None else problem.initial_pose
    if pose is None:
        raise ProblemError("initial_pose: missing")
    z = problem.points3d @ so3_exp(pose.rvec)[2] + pose.tvec[2]
    behind = np.flatnonzero(~(z > 0))
    if len(behind):
        names = ", ".join(f"points3d[{i}]" for i in behind[:_BEHIND_SHOWN])
        more = f" and {len(behind) - _BEHIND_SHOWN} more" if len(behind) > _BEHIND_SHOWN else ""
        raise ProblemError(f"{names}{more}: behind the camera at the initial pose "
                           "(camera z <= 0)")


def _pose_json(pose: PoseVectors) -> dict:
    return {"rvec": pose.rvec.tolist(), "tvec": pose.tvec.tolist()}


def problem_to_json(problem: Problem) -> dict:
    """The `snail-problem/1` object of a problem (synthetic scenes are written this way)."""
    K = problem.K
    camera = {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]),
              "cy": float(K[1, 2]), "dist": problem.dist.tolist()}
    if problem.image_size is not None:
        camera = {"width": problem.image_size[0], "height": problem.image_size[1], **camera}
    obj = {"format": FORMAT, "camera": camera,
           "points2d": problem.points2d.tolist(), "points3d": problem.points3d.tolist()}
    for key in ("initial_pose", "reference_pose"):
        pose = getattr(problem, key)
        if pose is not None:
            obj[key] = _pose_json(pose)
    return obj
