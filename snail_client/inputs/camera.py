"""Camera files (``snail-camera/1``): a problem's ``camera`` block on its own, so one
calibration serves every image of that camera (OpenCV pixel and distortion conventions)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from snail_common.loc.problem import ProblemError, parse_camera_block

from .fields import InputError, check_format, load, obj

FORMAT = "snail-camera/1"


@dataclass(frozen=True)
class Camera:
    """Intrinsics, OpenCV distortion (k1, k2, p1, p2[, k3, ...]) and image size."""

    K: np.ndarray  # (3, 3)
    dist: np.ndarray  # (k,), zeros(5) without distortion
    size: tuple[int, int] | None  # (width, height)

    def to_json(self) -> dict:
        """The ``snail-camera/1`` object, also a problem's ``camera`` block without
        ``format``."""
        out: dict[str, Any] = {"format": FORMAT}
        if self.size is not None:
            out.update(width=self.size[0], height=self.size[1])
        out.update(fx=float(self.K[0, 0]), fy=float(self.K[1, 1]), cx=float(self.K[0, 2]),
                   cy=float(self.K[1, 2]), dist=[float(d) for d in self.dist])
        return out


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def parse_camera(value: Any) -> Camera:
    """Validate a decoded ``snail-camera/1`` object (InputError names the field)."""
    cam = obj(value, "camera")
    check_format(cam, FORMAT)
    try:
        return Camera(*parse_camera_block(cam, where=""))
    except InputError:
        raise
    except ProblemError as exc:
        raise InputError(str(exc)) from None


def load_camera(path: str | Path) -> Camera:
    """A camera file; InputError prefixed with the file name."""
    return load(path, parse_camera)
