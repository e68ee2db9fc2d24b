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


DELIMITER_ROW = re.compile(r"^\|[-:| ]+\|$")


def _split_tables(path: Path) -> list[int]:
    """Delimiter rows followed by a blank line and more rows: the table ends at its
    header and its rows render as a paragraph of pipes."""
    lines = path.read_text().splitlines()
    return [i + 1 for i in range(len(lines) - 2)
            if DELIMITER_ROW.match(lines[i]) and not lines[i + 1].strip()
            and lines[i + 2].startswith("|")]


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(DOCS)) for p in PAGES])
def test_a_table_has_no_blank_line_after_its_header(page: Path):
    assert not _split_tables(page), (f"{page.relative_to(DOCS)}: remove the blank line "
                                     f"after the table header at lines "
                                     f"{_split_tables(page)}")


def test_the_check_sees_a_table_split_after_its_header(tmp_path: Path):
    page = tmp_path / "page.md"
    page.write_text("Text.\n\n| a | b |\n|---|---:|\n\n| 1 | 2 |\n\n| c |\n|---|\n| 3 |\n")
    assert _split_tables(page) == [4]
