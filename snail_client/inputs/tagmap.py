"""Tag maps (``snail-tagmap/1``): where each printed AprilTag is in the world.

A tag's pose maps its own frame to the world; its frame is OpenCV ArUco's, so the corners
of the black square (-s/2, s/2, 0), (s/2, s/2, 0), (s/2, -s/2, 0), (-s/2, -s/2, 0) come in
the order ArUco returns detected corners (top-left, top-right, bottom-right, bottom-left).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from snail_common.loc.geometry import so3_exp

from .fields import InputError, check_format, field, integer, load, numbers, obj, positive

FORMAT = "snail-tagmap/1"
FAMILIES = {"tag36h11": 587}  # family -> number of ids (OpenCV's DICT_APRILTAG_36h11)


@dataclass(frozen=True)
class Tag:
    id: int
    size: float  # side of the black square, metres
    rvec: np.ndarray  # tag frame -> world
    tvec: np.ndarray

    def corners_tag(self) -> np.ndarray:
        """The four corners in the tag's own frame, in ArUco's order (4, 3)."""
        h = self.size / 2
        return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])

    def corners_world(self) -> np.ndarray:
        """The four corners in the world, in ArUco's order (4, 3)."""
        return self.corners_tag() @ so3_exp(self.rvec).T + self.tvec


@dataclass(frozen=True)
class TagMap:
    family: str
    tags: dict[int, Tag]

    def to_json(self) -> dict:
        return {"format": FORMAT, "family": self.family,
                "tags": [{"id": t.id, "size": t.size, "rvec": t.rvec.tolist(),
                          "tvec": t.tvec.tolist()} for t in self.tags.values()]}


def parse_tagmap(value: Any) -> TagMap:
    """Validate a decoded ``snail-tagmap/1`` object (InputError names the field)."""
    top = obj(value, "tag map")
    check_format(top, FORMAT)
    family = field(top, "family")
    if not isinstance(family, str) or family not in FAMILIES:
        raise InputError(f"family: expected one of {sorted(FAMILIES)}, got {family!r}")
    raw = field(top, "tags")
    if not isinstance(raw, list) or not raw:
        raise InputError("tags: expected a non-empty list of tags")
    tags: dict[int, Tag] = {}
    for i, item in enumerate(raw):
        where = f"tags[{i}]"
        entry = obj(item, where)
        tag_id = integer(field(entry, "id", f"{where}."), f"{where}.id")
        if tag_id >= FAMILIES[family]:
            raise InputError(f"{where}.id: {tag_id} is not a {family} id "
                             f"(0..{FAMILIES[family] - 1})")
        if tag_id in tags:
            raise InputError(f"{where}.id: tag {tag_id} appears twice")
        tags[tag_id] = Tag(
            id=tag_id, size=positive(field(entry, "size", f"{where}."), f"{where}.size"),
            rvec=numbers(field(entry, "rvec", f"{where}."), 3, f"{where}.rvec"),
            tvec=numbers(field(entry, "tvec", f"{where}."), 3, f"{where}.tvec"))
    return TagMap(family, tags)


def load_tagmap(path: str | Path) -> TagMap:
    """A tag map file; InputError prefixed with the file name."""
    return load(path, parse_tagmap)
