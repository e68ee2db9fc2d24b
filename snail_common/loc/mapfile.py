"""Map-owner setting files (see shared/FORMATS.md): the map owner's ``snail-map/1`` (point
ids and 3D coordinates) and the device's ``snail-frame/1`` (2D points, camera, initial pose
and, per 2D point, the id of the map point it matches).

As for problem files, every check raises ProblemError naming the field at fault. Sizes are
bounded before any per-point work: a map owner's daemon reads the map once, but a frame
comes from a device. Ids are below 2^32 because they become 32-bit secret inputs of the
selection circuit (the device's ids compared with the map owner's).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import chain
from pathlib import Path
from typing import Any

import numpy as np

from .problem import (
    MIN_POINTS,
    PoseVectors,
    Problem,
    ProblemError,
    _field,
    _numbers,
    _object,
    _pose,
    _read,
    _rows,
    parse_camera_block,
    parse_json,
)

MAP_FORMAT = "snail-map/1"
FRAME_FORMAT = "snail-frame/1"
MAX_MAP_POINTS = 1_000_000
MAX_FRAME_POINTS = 65_536
MAX_ID = (1 << 32) - 1
MAX_FILE_BYTES = 256 << 20  # a million points pretty-printed fit with room to spare


@dataclass(frozen=True)
class MapPoints:
    """A map: ``ids[i]`` names the 3D point ``xyz[i]`` (ids distinct)."""

    ids: np.ndarray  # (M,) int64
    xyz: np.ndarray  # (M, 3) float64

    def select(self, ids: np.ndarray, where: str = "map_ids") -> np.ndarray:
        """The 3D points with the given ids, in that order (the cleartext selection the
        circuit computes obliviously); ProblemError naming the first id not in the map."""
        order = np.argsort(self.ids, kind="stable")
        sorted_ids = self.ids[order]
        pos = np.minimum(np.searchsorted(sorted_ids, ids), len(sorted_ids) - 1)
        missing = np.flatnonzero(sorted_ids[pos] != ids)
        if len(missing):
            i = int(missing[0])
            raise ProblemError(f"{where}[{i}]: map point {int(ids[i])} is not in the map")
        return self.xyz[order[pos]]


@dataclass(frozen=True)
class Frame:
    """A device's frame: its own data, and which map points (by id) its 2D points match."""

    K: np.ndarray  # (3, 3)
    dist: np.ndarray  # (k,)
    points2d: np.ndarray  # (n, 2) pixels
    map_ids: np.ndarray  # (n,) int64
    initial_pose: PoseVectors | None  # None only for frames after a sequence's first
    image_size: tuple[int, int] | None = None

    @property
    def n(self) -> int:
        return len(self.points2d)

    def problem(self, points: MapPoints) -> Problem:
        """The snail-problem this frame is once its map points are known (what the
        map-owner setting computes without anyone holding both: for tests and oracles)."""
        return Problem(K=self.K, dist=self.dist, points2d=self.points2d,
                       points3d=points.select(self.map_ids), initial_pose=self.initial_pose,
                       image_size=self.image_size)


def _format(obj: dict, expected: str) -> None:
    fmt = obj.get("format")
    if fmt != expected:
        raise ProblemError(f"format: expected {expected!r}, got {str(fmt)[:40]!r}")


def _list(value: Any, where: str, low: int, high: int) -> list:
    if not isinstance(value, list):
        raise ProblemError(f"{where}: expected a list, got {type(value).__name__}")
    if not low <= len(value) <= high:
        raise ProblemError(f"{where}: expected {low} to {high} entries, got {len(value)}")
    return value


def _id(value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_ID:
        raise ProblemError(f"{where}: expected an integer id in [0, {MAX_ID}], "
                           f"got {str(value)[:40]}")
    return value


def parse_map(obj: Any) -> MapPoints:
    """Validate a decoded ``snail-map/1`` object."""
    obj = _object(obj, "map")
    _format(obj, MAP_FORMAT)
    points = _list(_field(obj, "points", ""), "points", 1, MAX_MAP_POINTS)
    ids, xyz = _points_fast(points) or _points_checked(points)
    order = np.argsort(ids, kind="stable")
    dup = np.flatnonzero(ids[order][1:] == ids[order][:-1])
    if len(dup):
        first, second = sorted((int(order[dup[0]]), int(order[dup[0] + 1])))
        raise ProblemError(f"points[{second}].id: {int(ids[second])} is also "
                           f"points[{first}].id")
    return MapPoints(ids=ids, xyz=xyz)


def _points_fast(points: list) -> tuple[np.ndarray, np.ndarray] | None:
    """(ids, xyz) by whole-list type checks (a million points in about a second), or None
    when anything is off, and ``_points_checked`` finds and names it."""
    if any(type(p) is not dict for p in points):
        return None
    ids = [p.get("id") for p in points]
    rows = [p.get("xyz") for p in points]
    if any(type(i) is not int for i in ids) or any(
            type(r) is not list or len(r) != 3 for r in rows):
        return None
    flat = list(chain.from_iterable(rows))
    if not set(map(type, flat)) <= {int, float} or max(map(abs, ids)) > MAX_ID:
        return None
    xyz = np.array(flat, dtype=np.float64).reshape(len(points), 3)
    ids_arr = np.array(ids, dtype=np.int64)
    if not np.isfinite(xyz).all() or (ids_arr < 0).any():
        return None
    return ids_arr, xyz


def _points_checked(points: list) -> tuple[np.ndarray, np.ndarray]:
    """(ids, xyz) point by point, raising ProblemError at the first bad field."""
    ids = np.empty(len(points), dtype=np.int64)
    xyz = np.empty((len(points), 3))
    for i, point in enumerate(points):
        where = f"points[{i}]"
        point = _object(point, where)
        ids[i] = _id(_field(point, "id", f"{where}."), f"{where}.id")
        xyz[i] = _numbers(_field(point, "xyz", f"{where}."), 3, f"{where}.xyz")
    return ids, xyz


def parse_frame(obj: Any, *, require_initial_pose: bool = True) -> Frame:
    """Validate a decoded ``snail-frame/1`` object (a sequence's frames after the first
    may leave out the initial pose: they start from the track's prediction)."""
    obj = _object(obj, "frame")
    _format(obj, FRAME_FORMAT)
    K, dist, size = parse_camera_block(_field(obj, "camera", ""))
    raw2d = _list(_field(obj, "points2d", ""), "points2d", MIN_POINTS, MAX_FRAME_POINTS)
    p2 = _rows(raw2d, 2, "points2d")
    raw_ids = _list(_field(obj, "map_ids", ""), "map_ids", 0, MAX_FRAME_POINTS)
    if len(raw_ids) != len(p2):
        raise ProblemError(f"map_ids: {len(raw_ids)} ids but points2d has {len(p2)} points")
    ids = np.array([_id(v, f"map_ids[{i}]") for i, v in enumerate(raw_ids)], dtype=np.int64)
    if obj.get("initial_pose") is None and not require_initial_pose:
        pose = None
    else:
        pose = _pose(_field(obj, "initial_pose", ""), "initial_pose")
    return Frame(K=K, dist=dist, points2d=p2, map_ids=ids, initial_pose=pose,
                 image_size=size)


def _load(path: str | Path) -> Any:
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise ProblemError(f"{path}: cannot read ({exc})") from None
    if size > MAX_FILE_BYTES:
        raise ProblemError(f"{path}: {size} bytes, more than the {MAX_FILE_BYTES} read")
    return parse_json(_read(path))


def load_map(path: str | Path) -> MapPoints:
    """A ``snail-map/1`` file."""
    return parse_map(_load(path))


def load_frame(path: str | Path) -> Frame:
    """A ``snail-frame/1`` file."""
    return parse_frame(_load(path))
