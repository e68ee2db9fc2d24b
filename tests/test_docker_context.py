"""The image's build context and its Dockerfile agree: every path the Dockerfile copies
from the context is let through .dockerignore, and every role (a package run as ``python
-m snail_X``) is copied. snail_mapd was copied but ignored, and only the compose test,
which needs a container engine, found it."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _copied_from_context() -> list[str]:
    """Sources of the Dockerfile's COPY lines that read the build context."""
    sources = []
    for line in (ROOT / "Dockerfile").read_text().splitlines():
        words = line.split()
        if words[:1] == ["COPY"] and not any(w.startswith("--from=") for w in words):
            sources += [w.rstrip("/") for w in words[1:-1] if not w.startswith("--")]
    return sources


def test_every_copied_path_is_in_the_build_context():
    allowed = {line[1:].rstrip("/") for line in
               (ROOT / ".dockerignore").read_text().splitlines() if line.startswith("!")}
    copied = _copied_from_context()
    assert "snail_common" in copied
    assert [c for c in copied if c not in allowed] == []


def test_every_role_is_copied():
    roles = {p.parent.name for p in ROOT.glob("snail_*/__main__.py")}
    assert {"snail_garbler", "snail_evaluator", "snail_mapd"} <= roles
    assert roles - set(_copied_from_context()) == set()
