"""The README's and the performance page's headline tables are the one `snail-bench paper`
run in docs/paper/results.json (snail_bench.headline), so they agree with each other and
with the run, whose date, commit and machine they show."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from shared_paths import SHARED

from snail_bench.headline import between_markers, headline, provenance, rows

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs" / "paper" / "results.json"


@pytest.mark.parametrize("document", ["README.md", "docs/performance.md"])
def test_the_headline_table_is_the_paper_run(document: str):
    if not (SHARED / "paper_results.json").is_file():
        pytest.skip(f"no {SHARED / 'paper_results.json'} (set SNAIL_SHARED)")
    results = json.loads(RESULTS.read_text())
    expected = headline(results, json.loads((SHARED / "paper_results.json").read_text()))
    shown = between_markers((ROOT / document).read_text())
    assert shown is not None, f"{document} has no <!-- headline:begin/end --> block"
    assert shown == expected, (f"{document}'s headline is not {RESULTS.relative_to(ROOT)}'s: "
                               "run `python -m snail_bench.headline "
                               "docs/paper/results.json README.md docs/performance.md`")


def test_the_run_says_when_where_and_at_which_commit():
    results = json.loads(RESULTS.read_text())
    assert results["started"] and results["commit"] and results["machine"]
    text = headline(results, {})
    assert results["commit"] in text and results["machine"] in text
    assert results["started"] in text


def test_a_quick_run_shows_what_it_measured():
    quick = {"sweep": {"series": {"lm_0ms": [{"n": 6, "per_iteration_s": 0.08,
                                              "bytes": 8e6}]}},
             "totals": {"sil": {"a": {"algorithm": "lm", "n": 6, "total_s": 4.0}}}}
    table = rows(quick, {})
    assert [figure for figure, _, _ in table] == [
        "one LM iteration, n = 6 points", "garbled tables per iteration, n = 6",
        "one LM localization, n = 6..6"]
    assert table[0][1:] == ("0.080 s", "-")


def test_a_paper_run_records_its_commit_machine_and_engine(monkeypatch):
    found = provenance()
    assert found["commit"] and found["machine"]
    assert "cores" in found["machine"]
    monkeypatch.setenv("SNAIL_ENGINE", "numpy")
    assert provenance()["engine"] == "numpy (asked for)"
    assert "engine: numpy (asked for)" in headline(provenance(), {})


def test_the_update_rewrites_only_the_block(tmp_path: Path):
    from snail_bench.headline import BEGIN, END, main

    if not (SHARED / "paper_results.json").is_file():
        pytest.skip(f"no {SHARED / 'paper_results.json'} (set SNAIL_SHARED)")
    page = tmp_path / "page.md"
    page.write_text(f"# Title\n\n{BEGIN}\nold table\n{END}\n\nAfter.\n")
    assert main([str(RESULTS), str(page)]) == 0
    text = page.read_text()
    assert text.startswith("# Title\n\n") and text.endswith(f"{END}\n\nAfter.\n")
    assert "old table" not in text and between_markers(text) == headline(
        json.loads(RESULTS.read_text()), json.loads((SHARED / "paper_results.json").read_text()))
