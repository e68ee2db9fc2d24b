"""MkDocs hooks (mkdocs.yml ``hooks:``): the dated notes listed in the nav by themselves, and
a ``mermaid`` flowchart of subgraphs drawn as HTML.

Notes: every ``docs/notes/*.md`` (a dated page of development history) is put under the
nav's "Development notes", newest first, so a note needs no mkdocs.yml edit; every other
page must be in the nav by hand (a page left out fails ``mkdocs build --strict``).

Floors:
docs/architecture.md draws the floors of the code as a mermaid flowchart, which GitHub
renders. The site would need mermaid's JavaScript from a CDN for it (Material fetches it
at page load), and the site loads nothing from outside itself. So at build time each
``mermaid`` block becomes a stack of boxes: one row per ``subgraph`` (a floor, in the
order written), one box per node with its label, and under it the nodes it points to
(``a --> b``: "uses b"). Only that subset of the syntax is read; a block with anything
else stays as code with a warning (which fails `mkdocs build --strict`: extend the
hook), so it is never drawn wrongly.
"""

from __future__ import annotations

import html
import logging
import re
from pathlib import Path

log = logging.getLogger("mkdocs.hooks.floors")

BLOCK = re.compile(r"^```mermaid\n(.*?)^```\n", re.S | re.M)
SUBGRAPH = re.compile(r'^subgraph\s+(\w+)\["(.*)"\]$')
NODE = re.compile(r'^(\w+)\["(.*)"\]$')
EDGE = re.compile(r"^(\w+)\s*-->\s*(\w+)$")


NOTES_SECTION = "Development notes"


def on_config(config, **kwargs):
    """List every docs/notes/*.md under the nav's notes section, newest (by name) first."""
    notes_dir = Path(config["docs_dir"]) / "notes"
    section = next((entry for entry in config["nav"] or []
                    if isinstance(entry, dict) and NOTES_SECTION in entry), None)
    if section is None or not notes_dir.is_dir():
        return config
    listed = section[NOTES_SECTION] or []
    known = {next(iter(item.values())) if isinstance(item, dict) else item for item in listed}
    for page in sorted(notes_dir.glob("*.md"), reverse=True):
        path = f"notes/{page.name}"
        if path not in known:
            listed.append({page.stem: path})
    section[NOTES_SECTION] = sorted(
        listed, key=lambda item: next(iter(item.values())) if isinstance(item, dict) else item,
        reverse=True)
    return config


def _parse(source: str) -> tuple[list[tuple[str, list[str]]], dict[str, str],
                                  dict[str, list[str]]] | None:
    """(floors as (label, node ids), node labels, edges) or None for other syntax."""
    floors: list[tuple[str, list[str]]] = []
    labels: dict[str, str] = {}
    uses: dict[str, list[str]] = {}
    lines = [line.strip() for line in source.splitlines() if line.strip()]
    if not lines or lines[0] not in ("flowchart TB", "flowchart TD", "graph TB", "graph TD"):
        return None
    for line in lines[1:]:
        if match := SUBGRAPH.match(line):
            floors.append((match.group(2), []))
        elif line == "end":
            continue
        elif (match := NODE.match(line)) and floors:
            labels[match.group(1)] = match.group(2)
            floors[-1][1].append(match.group(1))
        elif match := EDGE.match(line):
            uses.setdefault(match.group(1), []).append(match.group(2))
        else:
            return None
    return floors, labels, uses


def _label(text: str) -> str:
    """A node label: the first line as the box's name, the rest below it."""
    first, *rest = text.split("<br/>")
    body = " ".join(html.escape(part) for part in rest)
    return f'<strong>{html.escape(first)}</strong><span>{body}</span>'


def _render(floors: list[tuple[str, list[str]]], labels: dict[str, str],
            uses: dict[str, list[str]]) -> str:
    rows = []
    for name, nodes in floors:
        boxes = []
        for node in nodes:
            used = ", ".join(html.escape(labels[u].split("<br/>")[0])
                             for u in uses.get(node, []) if u in labels)
            foot = f'<em>uses {used}</em>' if used else ""
            boxes.append(f'<div class="floor-box">{_label(labels[node])}{foot}</div>')
        rows.append(f'<div class="floor"><div class="floor-name">{html.escape(name)}</div>'
                    f'<div class="floor-boxes">{"".join(boxes)}</div></div>')
    return f'<div class="floors" markdown="0">{"".join(rows)}</div>\n'


def on_page_markdown(markdown: str, page, **kwargs) -> str:
    """Replace each readable mermaid block of a page by its boxes."""
    def replace(match: re.Match) -> str:
        parsed = _parse(match.group(1))
        if parsed is None:
            log.warning("%s: a mermaid block this hook cannot read stays as code",
                        page.file.src_uri)
            return match.group(0)
        return _render(*parsed)

    return BLOCK.sub(replace, markdown)
