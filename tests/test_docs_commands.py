"""The README's and the site's shell commands run as a user would type them: a command shown
to users that no longer works fails CI.

Every ``bash``/``sh``/``console``/``shell`` code block in README.md and docs/ (not the dated
development notes, which record history) carries a marker on the line before its fence:

- ``<!-- docs-test: run -->``: the block runs as one bash script (``set -e``, so every
  command must succeed) with this environment's programs on PATH, in a folder beside a
  ``shared`` folder (the docs' ``../shared``). The blocks of one page share their folder
  and run in the page's order, as a reader following the page would (run a block alone
  with -k and it may miss what an earlier one made).
- ``<!-- docs-test: run after-install -->``: the same, each line's leading
  ``python3 -m venv .venv && . .venv/bin/activate && pip install -e '...' &&`` dropped (this
  environment is that install); a line that is then the test suite itself
  (``python -m pytest``) is skipped, saying so: .ci/run runs the suite.
- ``<!-- docs-test: skip REASON -->``: not run (other hosts, root, a container engine); the
  reason is printed with the skip.

A block without a marker fails, so no command goes unchecked by oversight. Synopses of
options are ``text`` blocks. Commands use the smallest sizes that show the point.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from shared_paths import SHARED

ROOT = Path(__file__).resolve().parent.parent
SHELLS = ("bash", "sh", "console", "shell")
MARKER = re.compile(r"<!--\s*docs-test:\s*(run(?:\s+after-install)?|skip\s+(.+?))\s*-->")
INSTALL = re.compile(r"^python3 -m venv \.venv && \. \.venv/bin/activate && "
                     r"pip install -e '\.\[[a-z,]+\]' && ")
SUITE = re.compile(r"^python -m pytest\b")
TIMEOUT_S = 300  # a block waiting on a daemon that never came up fails in 5 min


@dataclass(frozen=True)
class Block:
    where: str      # file:line of the fence
    mode: str       # "run", "run after-install", "skip", or "" (no marker)
    reason: str     # why skipped
    script: str


def _documents() -> list[Path]:
    docs = sorted(p for p in (ROOT / "docs").rglob("*.md")
                  if "notes" not in p.relative_to(ROOT / "docs").parts)
    return [ROOT / "README.md", *docs]


def _blocks(path: Path) -> list[Block]:
    """The shell blocks of one Markdown file with the marker before each."""
    lines = path.read_text().splitlines()
    found, i = [], 0
    while i < len(lines):
        fence = re.match(r"^(\s*)(```+)\s*([\w-]*)", lines[i])
        if not fence:
            i += 1
            continue
        start, ticks, lang = i, fence.group(2), fence.group(3)
        i += 1
        body = []
        while i < len(lines) and not lines[i].strip().startswith(ticks):
            body.append(lines[i])
            i += 1
        i += 1
        if lang not in SHELLS:
            continue
        before = next((lines[j] for j in range(start - 1, -1, -1) if lines[j].strip()), "")
        marker = MARKER.search(before)
        mode = "" if not marker else "skip" if marker.group(2) else " ".join(
            marker.group(1).split())
        where = f"{path.relative_to(ROOT)}:{start + 1}"
        found.append(Block(where, mode, marker.group(2) if marker and marker.group(2) else "",
                           "\n".join(body)))
    return found


BLOCKS = [block for path in _documents() for block in _blocks(path)]


def _script(block: Block) -> tuple[str, list[str]]:
    """The bash script to run and the lines left out, with why."""
    if block.mode != "run after-install":
        return block.script, []
    kept, left_out = [], []
    for line in block.script.splitlines():
        line = INSTALL.sub("", line)
        if SUITE.match(line):
            left_out.append(f"{line!r}: the test suite itself (.ci/run runs it)")
            continue
        kept.append(line)
    return "\n".join(kept), left_out


def test_the_docs_show_commands():
    assert len(BLOCKS) >= 10, [b.where for b in BLOCKS]
    assert any(b.where.startswith("README.md") and b.mode == "run after-install"
               for b in BLOCKS), "the README's quick start is not run"


def test_every_shell_block_is_marked():
    unmarked = [b.where for b in BLOCKS if not b.mode]
    assert not unmarked, ("shell blocks without a '<!-- docs-test: run -->' or "
                          f"'<!-- docs-test: skip REASON -->' line before them: {unmarked}")


@pytest.fixture(scope="module")
def folders(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """One working folder per page, made on first use."""
    return {}


def _folder(folders: dict[str, Path], page: str,
            tmp_path_factory: pytest.TempPathFactory) -> Path:
    if page not in folders:
        top = tmp_path_factory.mktemp("docs-page")
        (top / "shared").symlink_to(SHARED)
        (top / "work").mkdir()
        folders[page] = top / "work"
    return folders[page]


@pytest.mark.parametrize("block", [b for b in BLOCKS if b.mode],
                         ids=[b.where for b in BLOCKS if b.mode])
def test_command_works_as_shown(block: Block, folders: dict[str, Path],
                                tmp_path_factory: pytest.TempPathFactory):
    if block.mode == "skip":
        pytest.skip(f"{block.where}: {block.reason}")
    if not (SHARED / "examples").is_dir():
        pytest.skip(f"no shared folder at {SHARED} (set SNAIL_SHARED): the docs' "
                    "../shared/examples")
    script, left_out = _script(block)
    for note in left_out:
        print(f"{block.where}: not run: {note}")
    work = _folder(folders, block.where.rsplit(":", 1)[0], tmp_path_factory)
    env = {**os.environ,
           "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    try:
        done = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", script], cwd=work,
                              env=env, capture_output=True, text=True, timeout=TIMEOUT_S,
                              stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f"{block.where}: still running after {TIMEOUT_S} s:\n{script}\n"
                    f"{exc.stdout or ''}{exc.stderr or ''}")
    assert done.returncode == 0, (f"{block.where} failed (exit {done.returncode}):\n{script}\n"
                                  f"--- stdout\n{done.stdout[-3000:]}\n"
                                  f"--- stderr\n{done.stderr[-3000:]}")


def test_the_readme_links_resolve():
    text = (ROOT / "README.md").read_text()
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    missing = [t for t in targets if "://" not in t and not (ROOT / t).exists()]
    assert targets and not missing, missing
