"""The floors the site draws (docs_hooks.py, from docs/architecture.md's mermaid block) are
the floors tests/test_layers.py enforces: every package in its box on its floor."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from test_layers import FLOORS

ROOT = Path(__file__).resolve().parent.parent
_spec = importlib.util.spec_from_file_location("docs_hooks", ROOT / "docs_hooks.py")
docs_hooks = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(docs_hooks)
BLOCK, _parse, on_page_markdown = docs_hooks.BLOCK, docs_hooks._parse, docs_hooks.on_page_markdown


class _Page:
    class file:  # mkdocs' page.file.src_uri
        src_uri = "architecture.md"


def test_the_drawn_floors_are_the_enforced_ones():
    markdown = (ROOT / "docs" / "architecture.md").read_text()
    parsed = _parse(BLOCK.search(markdown).group(1))
    assert parsed is not None, "docs_hooks cannot read the architecture's mermaid block"
    floors, labels, _ = parsed
    drawn = {labels[node].split("<br/>")[0]: int(name.split(" ")[0])
             for name, nodes in floors for node in nodes}
    enforced = {package.removeprefix("snail_common."): floor
                for package, floor in FLOORS.items()}
    assert drawn == enforced


def test_the_page_gets_boxes_and_no_mermaid():
    html = on_page_markdown((ROOT / "docs" / "architecture.md").read_text(), _Page)
    assert "```mermaid" not in html
    assert html.count('class="floor"') == len(set(FLOORS.values()))
    assert '<strong>snail_client</strong>' in html and "uses loc, net, gc, ot" in html


def test_other_syntax_stays_as_code(caplog):
    markdown = "```mermaid\nsequenceDiagram\n  a->>b: hi\n```\n"
    assert on_page_markdown(markdown, _Page) == markdown
    assert "cannot read" in caplog.text


def test_every_note_is_in_the_nav_newest_first(tmp_path: Path):
    (tmp_path / "notes").mkdir()
    for name in ("2026-11-26.md", "2026-11-27-net.md", "2026-11-27-docs.md"):
        (tmp_path / "notes" / name).write_text("# a note\n")
    nav = [{"Home": "index.md"},
           {docs_hooks.NOTES_SECTION: [{"2026-11-26": "notes/2026-11-26.md"}]}]
    config = docs_hooks.on_config({"docs_dir": str(tmp_path), "nav": nav})
    assert config["nav"][0] == {"Home": "index.md"}
    assert [next(iter(item.values())) for item in config["nav"][1][docs_hooks.NOTES_SECTION]] \
        == ["notes/2026-11-27-net.md", "notes/2026-11-27-docs.md", "notes/2026-11-26.md"]
