"""The command line's input flags: ``localize --input``, ``--image`` with ``--tag-map`` and
``--camera``, or ``--colmap`` with ``--image-name``; ``track --input`` or ``--image-dir``.
Which go together is checked here so the commands stay about running frames."""

from __future__ import annotations

from collections.abc import Callable

import click

from snail_common.loc.problem import Problem, ProblemError, load_problem, read_sequence

from .colmap import colmap_problem, read_model
from .sources import image_problem, image_sequence, load_image_inputs, save_problem

_FILE = click.Path(exists=True, dir_okay=False)


def _decorate(fn: Callable, decorators: list[Callable]) -> Callable:
    for decorate in reversed(decorators):
        fn = decorate(fn)
    return fn


def _image_inputs() -> list[Callable]:
    return [
        click.option("--tag-map", type=_FILE, metavar="MAP.json",
                     help="Where the AprilTags are (snail-tagmap/1)."),
        click.option("--camera", type=_FILE, metavar="CAM.json",
                     help="The camera's intrinsics and distortion (snail-camera/1)."),
    ]


def localize_inputs(fn: Callable) -> Callable:
    """--input, --image with --tag-map and --camera, or --colmap with --image-name."""
    return _decorate(fn, [
        click.option("--input", "input_path", type=_FILE,
                     help="Problem file (snail-problem/1 JSON)."),
        click.option("--image", type=_FILE, metavar="IMG",
                     help="Camera image with AprilTag 36h11 markers (needs --tag-map and "
                          "--camera): the tags' corners are matched to the map and a first "
                          "pose is found in the clear (IPPE), on this machine."),
        *_image_inputs(),
        click.option("--colmap", type=click.Path(exists=True, file_okay=False),
                     metavar="DIR",
                     help="COLMAP sparse model folder (cameras, images, points3D; .bin or "
                          ".txt): localize one of its images (--image-name) from its "
                          "2D-3D matches; the model's pose becomes the reference pose."),
        click.option("--image-name", metavar="NAME", help="The COLMAP image to localize."),
        click.option("--max-points", type=click.IntRange(4, 100000), metavar="N",
                     help="Use the N model points seen in most images (default: all)."),
        click.option("--save-problem", type=click.Path(dir_okay=False), metavar="P.json",
                     help="Write the snail-problem/1 built from --image or --colmap, to "
                          "replay the run."),
    ])


def track_inputs(fn: Callable) -> Callable:
    """--input, or --image-dir with --tag-map and --camera."""
    return _decorate(fn, [
        click.option("--input", "input_path", type=click.Path(exists=True),
                     help="Sequence: JSON Lines, a JSON array of problems, one problem, or "
                          "a folder of problem files (name order)."),
        click.option("--image-dir", type=click.Path(exists=True, file_okay=False),
                     metavar="DIR",
                     help="A folder of camera images taken in name order (needs --tag-map "
                          "and --camera); each frame starts from the last trusted pose."),
        *_image_inputs(),
    ])


def _one_source(sources: dict[str, str | None]) -> str:
    given = [flag for flag, value in sources.items() if value]
    if len(given) != 1:
        raise click.UsageError(f"give exactly one of {', '.join(sources)}"
                               + (f" (got {', '.join(given)})" if given else ""))
    return given[0]


_NEEDS = {"--image": ("--tag-map", "--camera"), "--image-dir": ("--tag-map", "--camera"),
          "--colmap": ("--image-name",), "--input": ()}
_ONLY_WITH = {"--tag-map": ("--image", "--image-dir"), "--camera": ("--image", "--image-dir"),
              "--image-name": ("--colmap",), "--max-points": ("--colmap",),
              "--save-problem": ("--image", "--colmap")}


def _key(flag: str) -> str:
    return flag[2:].replace("-", "_")


def _check_flags(kw: dict, source: str) -> None:
    """The flags a source needs are there, and no flag of another source is."""
    missing = [f for f in _NEEDS[source] if not kw.get(_key(f))]
    if missing:
        raise click.UsageError(f"{source} needs {' and '.join(missing)}")
    for flag, sources in _ONLY_WITH.items():
        if kw.get(_key(flag)) is not None and source not in sources:
            raise click.UsageError(f"{flag}: only with {' or '.join(sources)}")


def load_frame(input_path: str | None, kw: dict) -> tuple[str, Problem]:
    """(what to name in messages, the problem) for ``localize``; ProblemError names the
    file at fault, click.UsageError a flag."""
    flag = _one_source({"--input": input_path, "--image": kw.get("image"),
                        "--colmap": kw.get("colmap")})
    _check_flags(kw, flag)
    if flag == "--input":
        try:
            return input_path, load_problem(input_path)
        except ProblemError as exc:
            raise ProblemError(f"{input_path}: {exc}") from None
    if flag == "--image":
        tagmap, camera = load_image_inputs(kw["tag_map"], kw["camera"])
        name, problem = kw["image"], image_problem(kw["image"], tagmap, camera)
    else:
        name = f"{kw['colmap']} ({kw['image_name']})"
        problem = colmap_problem(read_model(kw["colmap"]), kw["image_name"], kw["max_points"])
    if kw.get("save_problem"):
        save_problem(problem, kw["save_problem"])
    return name, problem


def load_frames(input_path: str | None, kw: dict
                ) -> list[tuple[str, Problem | ProblemError | Callable[[], Problem]]]:
    """``track``'s named frames: a problem, the ProblemError of one that cannot be read,
    or (an image) what builds it when the tracker takes it."""
    flag = _one_source({"--input": input_path, "--image-dir": kw.get("image_dir")})
    _check_flags(kw, flag)
    if flag == "--input":
        try:
            return read_sequence(input_path)
        except ProblemError as exc:
            raise ProblemError(f"{input_path}: {exc}") from None
    tagmap, camera = load_image_inputs(kw["tag_map"], kw["camera"])
    return image_sequence(kw["image_dir"], tagmap, camera)
