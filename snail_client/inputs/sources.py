"""Where a frame comes from: a problem file, a camera image with a tag map, or a COLMAP
model's image; and sequences of images for ``track``. Every failure is an InputError (a
ProblemError) whose text starts with the file or flag at fault."""

from __future__ import annotations

import functools
import json
from collections.abc import Callable
from pathlib import Path

from snail_common.loc.problem import Problem, problem_to_json

from .apriltag import problem_from_image, read_image
from .camera import Camera, load_camera
from .fields import InputError
from .tagmap import TagMap, load_tagmap

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


def image_problem(image: str | Path, tagmap: TagMap, camera: Camera) -> Problem:
    """The problem of one image file (InputError prefixed with the image's name)."""
    try:
        problem, _ = problem_from_image(read_image(image), tagmap, camera)
    except InputError as exc:
        text = str(exc)
        raise InputError(text if text.startswith(f"{image}:") else f"{image}: {text}") from None
    return problem


def load_image_inputs(tag_map: str, camera: str) -> tuple[TagMap, Camera]:
    return load_tagmap(tag_map), load_camera(camera)


def image_files(directory: str | Path) -> list[Path]:
    """The images of a folder in name order; InputError when there are none."""
    folder = Path(directory)
    if not folder.is_dir():
        raise InputError(f"{directory}: not a folder")
    files = sorted(p for p in folder.iterdir()
                   if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise InputError(f"{directory}: no images ({', '.join(IMAGE_SUFFIXES)})")
    return files


def image_sequence(directory: str | Path, tagmap: TagMap,
                   camera: Camera) -> list[tuple[str, Callable[[], Problem]]]:
    """``track``'s frames from a folder of images, each named by its file and built when
    the tracker takes it (reading and detection are part of its latency), on its own: an
    image without a mapped tag is reported and the others still run."""
    return [(path.name, functools.partial(image_problem, path, tagmap, camera))
            for path in image_files(directory)]


def save_problem(problem: Problem, path: str | Path) -> None:
    """Write the snail-problem/1 a run was built from, so it can be replayed."""
    try:
        Path(path).write_text(json.dumps(problem_to_json(problem), indent=1) + "\n")
    except OSError as exc:
        raise InputError(f"--save-problem: cannot write {path} ({exc.strerror})") from None
