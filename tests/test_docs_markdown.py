"""Markdown that GitHub renders but the site's Python-Markdown does not: a list or a table
right after a paragraph line or a code fence runs into the paragraph on the site. Every
page under docs/ keeps a blank line before them (the site's build cannot see this)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parent.parent / "docs"
PAGES = sorted(DOCS.rglob("*.md"))
STARTS_BLOCK = re.compile(r"^(- |\* |\d+\. |\|)")
CONTINUES = re.compile(r"^(\s+|- |\* |\d+\. |\||<!--)")


def _glued(path: Path) -> list[int]:
    """Lines that start a list or table glued to the line before."""
    lines, fence, bad = path.read_text().splitlines(), False, []
    for i, line in enumerate(lines):
        if line.lstrip().startswith("```"):
            fence = not fence
            continue
        if fence or not i or not STARTS_BLOCK.match(line):
            continue
        before = lines[i - 1]
        if before.strip() and not CONTINUES.match(before):
            bad.append(i + 1)
    return bad


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(DOCS)) for p in PAGES])
def test_lists_and_tables_start_their_own_block(page: Path):
    assert not _glued(page), (f"{page.relative_to(DOCS)}: add a blank line before lines "
                              f"{_glued(page)}")


def test_the_check_sees_a_glued_list(tmp_path: Path):
    page = tmp_path / "page.md"
    page.write_text("Some text:\n- an item\n\n```\ncode\n```\n| a | b |\n")
    assert _glued(page) == [2, 7]
