"""snail-bench paper: the counts it reports, its figures and report from given results,
and its refusal of a missing paper file. The measurements themselves are the service and
netem benchmarks' (tested there)."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from snail_bench.cli import main
from snail_bench.ops import ops_report
from snail_bench.paper import PAPER_RESULTS, load_paper, micro_benchmark, op_counts
from snail_common.pnp.spec import Spec


def test_op_counts_grow_by_the_same_amount_per_point():
    counts = {n: op_counts(Spec("lm", "sil", "ldlt", n)) for n in (6, 12, 18)}
    assert set(counts[6]) >= {"add", "mul", "div", "sub"}
    for op in counts[6]:
        step = counts[12][op] - counts[6][op]
        assert counts[18][op] - counts[12][op] == step, op
    assert counts[12]["mul"] > counts[6]["mul"]


def test_micro_benchmark_garbles_the_catalogue_ops():
    micro = micro_benchmark(4)
    ops = ops_report()["ops"]
    assert micro["float32"]["add"]["and_per_op"] == ops["add"]["and"]
    assert micro["float32"]["mul"]["and_per_op"] == ops["mul"]["and"]
    assert micro["int32"]["add"]["and_per_op"] == 31  # a ripple-carry adder, top carry free
    assert all(v["seconds_10000"] > 0 for kind in micro.values() for v in kind.values())


def _results() -> dict:
    sweep = {f"{alg}_{d}": [{"n": n, "per_iteration_s": 0.1 * n, "and": 1000 * n,
                             "bytes": 32000 * n} for n in (6, 56)]
             for alg in ("lm",) for d in ("0ms", "5ms")}
    return {
        "started": "then", "finished": "now",
        "ops": {"lm": {"6": op_counts(Spec("lm", "sil", "ldlt", 6)),
                       "56": op_counts(Spec("lm", "sil", "ldlt", 56))}},
        "micro": {k: {op: {"and_per_op": 10, "seconds_10000": 0.5} for op in ("add", "mul")}
                  for k in ("float32", "int32", "int64")},
        "totals": {"sil": {"lm-sil-ldlt-n6": {"algorithm": "lm", "n": 6, "total_s": 4.61,
                                              "per_iteration_s": 0.2, "and": 5}},
                   "do": {"lm-do-ldlt-n6": {"algorithm": "lm", "n": 6, "total_s": 45.94,
                                            "and": 9}}},
        "sweep": {"lab": "unavailable: test", "series": sweep},
        "latency": {"lab": "unavailable: test"},
    }


def test_figures_and_report_from_results(tmp_path):
    pytest.importorskip("matplotlib", reason="the bench extra (matplotlib) is not installed")
    from snail_bench import paper_plot

    sections = paper_plot.write_figures(_results(), load_paper(PAPER_RESULTS), tmp_path)
    for name in ("sil_vs_do", "seconds_per_iteration", "bytes_per_iteration",
                 "ops_per_iteration", "float_vs_int"):
        png = tmp_path / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    text = "\n".join(sections)
    # paper 9.22 s for SIL LM at n=6 and 459.4 s for DO: the ratios ours / paper
    assert "| SIL LM | 6 | 9.22 | 4.61 | 0.5 |" in text
    assert "| DO LM | 6 | 459.4 | 45.94 | 0.1 |" in text
    assert "Not measured: unavailable: test" in text


def test_a_missing_paper_file_is_one_line_exit_2(tmp_path):
    missing = tmp_path / "nope.json"
    result = CliRunner().invoke(main, ["paper", "--out", str(tmp_path / "o"),
                                       "--paper-results", str(missing)])
    assert result.exit_code == 2
    assert str(missing) in result.output and "Traceback" not in result.output
    assert not (tmp_path / "o").exists()


def test_the_paper_file_is_the_shared_one():
    assert json.loads(PAPER_RESULTS.read_text())["emp_sil_0ms"]["n"][0] == 6


def test_every_series_is_drawn_in_a_style_of_its_own(tmp_path, monkeypatch):
    """Ours LM and GN per iteration differ by a few AND gates: drawn alike, LM vanished
    under GN. Each series now has its own line style, marker and colour."""
    pytest.importorskip("matplotlib", reason="the bench extra (matplotlib) is not installed")
    from snail_bench import paper_plot

    styles: dict[str, list[tuple]] = {}
    save = paper_plot._save

    def keep(plt, fig, out, name):
        styles[name] = [(tuple(line.get_xdata()), tuple(line.get_ydata()),
                         line.get_linestyle(), line.get_marker())
                        for ax in fig.axes for line in ax.get_lines()]
        save(plt, fig, out, name)

    monkeypatch.setattr(paper_plot, "_save", keep)
    results = _results()
    series = results["sweep"]["series"]
    for d in ("0ms", "5ms"):  # GN exactly where LM is: the case that hid LM
        series[f"gn_{d}"] = [dict(r) for r in series[f"lm_{d}"]]
    results["totals"]["sil"]["gn-sil-ldlt-n6"] = {"algorithm": "gn", "n": 6,
                                                  "total_s": 4.61, "per_iteration_s": 0.2,
                                                  "and": 5}
    paper_plot.write_figures(results, load_paper(PAPER_RESULTS), tmp_path)
    coinciding = 0
    for name, lines in styles.items():
        for i, a in enumerate(lines):
            for b in lines[i + 1:]:
                if a[:2] == b[:2]:  # drawn at the same points: the styles must differ
                    coinciding += 1
                    assert a[2:] != b[2:], (name, a[2:])
    assert coinciding >= 3  # ours LM and GN at 0 and 5 ms, bytes per iteration


def test_the_profiles_figure_sets_each_localization_against_its_bound(tmp_path):
    pytest.importorskip("matplotlib", reason="the bench extra (matplotlib) is not installed")
    from snail_bench import paper_plot

    def loc(wall: float, bound: float) -> dict:
        return {"wall_s": wall, "link_bound_s": bound, "bound_ratio": round(wall / bound, 3),
                "invocations": 20, "bytes": {"garbler_to_evaluator": 112_500_000}}

    results = _results()
    results["profiles"] = {"points": [6, 12], "region": {"localization": {
        "6": loc(1.1, 0.9), "12": loc(1.5, 1.2)}}}
    text = "\n".join(paper_plot.write_figures(results, load_paper(PAPER_RESULTS), tmp_path))
    assert (tmp_path / "profiles.png").read_bytes()[:4] == b"\x89PNG"
    assert "| region | 6 | 20 | 112.5 | 0.900 | 1.100 | 1.22 |" in text
