"""Figures and report of ``snail-bench paper``: the paper's series beside ours.

One PNG per figure (titles, units, log axes where values span decades) and ``report.md``
with a table per figure: the paper's value, ours and the ratio ours / paper.
Needs matplotlib (the ``bench`` extra).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

PAPER_STYLE = {"linestyle": "--", "marker": "s", "alpha": 0.8}
OURS_STYLE = {"linestyle": "-", "marker": "o"}
# series that may coincide (ours LM and GN per iteration differ by a few AND gates) each
# get their own line style and an unfilled marker of their own shape, so one drawn over
# another still shows both; the colour tells the delay apart too
_LINES = {("paper", "lm"): "--", ("paper", "gn"): "-.", ("ours", "lm"): "-",
          ("ours", "gn"): ":"}
_MARKERS = {("paper", "lm", "0ms"): "s", ("paper", "gn", "0ms"): "D",
            ("paper", "lm", "5ms"): "v", ("paper", "gn", "5ms"): "*",
            ("ours", "lm", "0ms"): "o", ("ours", "gn", "0ms"): "x",
            ("ours", "lm", "5ms"): "^", ("ours", "gn", "5ms"): "+"}
_COLORS = {"": "C0", "0ms": "C0", "5ms": "C3"}


def series_style(source: str, alg: str, phase: str = "") -> dict:
    """Line style, marker and colour of one series: unique per (source, algorithm,
    delay), markers unfilled and GN's drawn above LM's."""
    color = _COLORS[phase] if source == "ours" else {"0ms": "C7", "5ms": "C1", "": "C7"}[
        phase]
    marker = _MARKERS[source, alg, phase or "0ms"]
    return {"linestyle": _LINES[source, alg], "marker": marker,
            "markersize": 9 if alg == "lm" else 7, "markerfacecolor": "none",
            "markeredgewidth": 1.5, "color": color, "zorder": 3 if alg == "gn" else 2,
            "alpha": 0.8 if source == "paper" else 1.0}


def _pyplot():
    try:
        import matplotlib
    except ImportError:
        raise ImportError("plotting needs matplotlib: pip install 'snail[bench]'") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _ratio(ours: float | None, paper: float | None) -> str:
    if not ours or not paper:
        return "-"
    return f"{ours / paper:.3g}"


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.4g}"


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---:|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def write_figures(results: dict, paper: dict, out: Path) -> list[str]:
    """Draw every figure into ``out``; returns the report's sections (markdown)."""
    plt = _pyplot()
    sections = [_sil_vs_do(plt, results, paper, out), _per_iteration(plt, results, paper, out),
                _bytes(plt, results, paper, out), _ops(plt, results, paper, out),
                _micro(plt, results, paper, out), _latency(plt, results, out),
                _profiles(plt, results, out)]
    return [s for s in sections if s]


def _save(plt, fig, out: Path, name: str) -> None:
    fig.tight_layout()
    fig.savefig(out / name, dpi=110)
    plt.close(fig)


def _sil_vs_do(plt, results: dict, paper: dict, out: Path) -> str:
    ref = paper["emp_do_vs_sil"]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for alg in ("lm", "gn"):
        ax.plot(ref["n"], ref[f"{alg}_sil_total_s"], label=f"paper SIL {alg.upper()}",
                **series_style("paper", alg, "0ms"))
        ax.plot(ref["n"], ref[f"{alg}_do_total_s"], label=f"paper DO {alg.upper()}",
                **series_style("paper", alg, "5ms"))
    sil = results["totals"]["sil"].values()
    do = results["totals"]["do"].values()
    for alg in ("lm", "gn"):
        mine = sorted((r["n"], r["total_s"]) for r in sil if r["algorithm"] == alg)
        if mine:
            ax.plot(*zip(*mine), label=f"ours SIL {alg.upper()}",
                    **series_style("ours", alg, "0ms"))
    mine_do = sorted((r["n"], r["total_s"]) for r in do)
    if mine_do:
        ax.plot(*zip(*mine_do), label="ours DO LM", **series_style("ours", "lm", "5ms"))
    ax.set(yscale="log", xlabel="points n", ylabel="one localization (s, log)",
           title="SIL (>= 20 invocations) vs data-oblivious (one circuit)")
    ax.legend(fontsize=8)
    _save(plt, fig, out, "sil_vs_do.png")
    rows = []
    for r in sorted(sil, key=lambda r: (r["algorithm"], r["n"])):
        p = _at(ref["n"], ref[f"{r['algorithm']}_sil_total_s"], r["n"])
        rows.append([f"SIL {r['algorithm'].upper()}", str(r["n"]), _fmt(p), _fmt(r["total_s"]),
                     _ratio(r["total_s"], p)])
    for r in sorted(do, key=lambda r: r["n"]):
        p = _at(ref["n"], ref["lm_do_total_s"], r["n"])
        rows.append(["DO LM", str(r["n"]), _fmt(p), _fmt(r["total_s"]), _ratio(r["total_s"], p)])
    return ("## SIL vs DO: one localization (s), loopback\n\n![](sil_vs_do.png)\n\n"
            + _table(["mode", "n", "paper", "ours", "ours/paper"], rows))


def _at(ns: list[int], values: list[float], n: int) -> float | None:
    return values[ns.index(n)] if n in ns else None


def _series(results: dict) -> dict[str, list[dict]]:
    return results["sweep"]["series"]


def _per_iteration(plt, results: dict, paper: dict, out: Path) -> str:
    fig, ax = plt.subplots(figsize=(7, 4.5))
    rows = []
    for phase, key in (("0ms", "emp_sil_0ms"), ("5ms", "emp_sil_5ms")):
        ref = paper[key]
        for alg in ("lm", "gn"):
            ax.plot(ref["n"], ref[f"{alg}_s_per_iteration"],
                    label=f"paper {alg.upper()} {phase}", **series_style("paper", alg, phase))
            mine = _series(results).get(f"{alg}_{phase}", [])
            if mine:
                ax.plot([r["n"] for r in mine], [r["per_iteration_s"] for r in mine],
                        label=f"ours {alg.upper()} {phase}", **series_style("ours", alg, phase))
            for r in mine:
                p = _at(ref["n"], ref[f"{alg}_s_per_iteration"], r["n"])
                rows.append([alg.upper(), phase, str(r["n"]), _fmt(p),
                             _fmt(r["per_iteration_s"]), _ratio(r["per_iteration_s"], p)])
    ax.set(yscale="log", xlabel="points n", ylabel="seconds per iteration (log)",
           title="One secure iteration, 2.5 Gbit/s between the servers, 0 / 5 ms one way")
    ax.legend(fontsize=8, ncol=2)
    _save(plt, fig, out, "seconds_per_iteration.png")
    lab = results["sweep"]["lab"]
    note = f"\n\nLab: {lab}" if isinstance(lab, str) else ""
    return ("## Seconds per iteration vs n\n\n![](seconds_per_iteration.png)" + note + "\n\n"
            + _table(["alg", "delay", "n", "paper", "ours", "ours/paper"], rows))


def _bytes(plt, results: dict, paper: dict, out: Path) -> str:
    ref = paper["emp_sil_0ms"]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    rows = []
    for alg in ("lm", "gn"):
        ax.plot(ref["n"], ref[f"{alg}_bytes_per_iteration"], label=f"paper {alg.upper()}",
                **series_style("paper", alg))
        mine = _series(results).get(f"{alg}_0ms", [])
        if mine:
            ax.plot([r["n"] for r in mine], [r["bytes"] for r in mine],
                    label=f"ours {alg.upper()}", **series_style("ours", alg))
        for r in mine:
            p = _at(ref["n"], ref[f"{alg}_bytes_per_iteration"], r["n"])
            rows.append([alg.upper(), str(r["n"]), _fmt(p), _fmt(r["bytes"]),
                         _ratio(r["bytes"], p)])
    ax.set(yscale="log", xlabel="points n", ylabel="bytes garbler -> evaluator (log)",
           title="Garbled tables per iteration")
    ax.legend(fontsize=8)
    _save(plt, fig, out, "bytes_per_iteration.png")
    return ("## Bytes garbler -> evaluator per iteration\n\n![](bytes_per_iteration.png)\n\n"
            + _table(["alg", "n", "paper", "ours", "ours/paper"], rows))


def _ops(plt, results: dict, paper: dict, out: Path) -> str:
    ref = paper["lm_ops_per_iteration"]
    counts = results["ops"].get("lm", {})
    ns = sorted(int(n) for n in counts)
    if not ns:
        return ""
    fig, ax = plt.subplots(figsize=(7, 4.5))
    grid = np.linspace(min(ns), max(ns), 50)
    rows = []
    for op, color in zip(("mul", "add", "sub", "div"), ("C0", "C1", "C2", "C3")):
        a, b = ref[op]
        ax.plot(grid, a + b * grid, color=color, label=f"paper {op}", **{**PAPER_STYLE,
                                                                        "marker": None})
        mine = [counts[n if n in counts else str(n)].get(op, 0) for n in ns]
        ax.plot(ns, mine, color=color, label=f"ours {op}", **OURS_STYLE)
        for n, v in zip(ns, mine):
            rows.append([op, str(n), _fmt(a + b * n), str(v), _ratio(v, a + b * n)])
    ax.set(yscale="log", xlabel="points n", ylabel="float32 operations per iteration (log)",
           title="Arithmetic per LM iteration")
    ax.legend(fontsize=8, ncol=2)
    _save(plt, fig, out, "ops_per_iteration.png")
    return ("## float32 operations per LM iteration\n\n![](ops_per_iteration.png)\n\n"
            "Ours counted on the float32 mirror of the algorithm; the circuit computes the "
            "Jacobian and the sums over points in fixed point (13-bit products, integer "
            "sums), counted here as the float operations they replace.\n\n"
            + _table(["op", "n", "paper", "ours", "ours/paper"], rows))


def _micro(plt, results: dict, paper: dict, out: Path) -> str:
    ref = paper["float_vs_fixed_10000_ops_s"]
    kinds = [k for k in ("float32", "int32", "int64") if k in results["micro"]]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    width = 0.2
    rows = []
    for i, op in enumerate(ref["ops"]):
        x = np.arange(len(kinds))
        paper_vals = [ref[k][i] for k in kinds]
        ours = [results["micro"][k][op]["seconds_10000"] for k in kinds]
        ax.bar(x + (2 * i - 1.5) * width, paper_vals, width, label=f"paper {op}", alpha=0.6)
        ax.bar(x + (2 * i - 0.5) * width, ours, width, label=f"ours {op}")
        for k, p, v in zip(kinds, paper_vals, ours):
            rows.append([op, k, _fmt(p), _fmt(v), _ratio(v, p),
                         str(results["micro"][k][op]["and_per_op"])])
    ax.set_xticks(np.arange(len(kinds)), kinds)
    ax.set(yscale="log", ylabel="seconds for 10,000 garbled ops (log)",
           title="float vs integer operations, garbled and evaluated")
    ax.legend(fontsize=8)
    _save(plt, fig, out, "float_vs_int.png")
    return ("## float vs integer: 10,000 garbled operations (s)\n\n![](float_vs_int.png)\n\n"
            + _table(["op", "type", "paper", "ours", "ours/paper", "our AND/op"], rows))


def _latency(plt, results: dict, out: Path) -> str:
    lat = results.get("latency", {})
    if "server" not in lat:
        return f"## Latency sweep\n\nNot measured: {lat.get('lab', 'no lab')}"
    delays = lat["delays_ms"]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for side in ("server", "client"):
        ax.plot(delays, lat[side]["per_iteration_s"], label=f"delay on the {side} link(s)",
                **OURS_STYLE)
        ax.plot(delays, lat[side]["beyond_evaluate_s"], label=f"{side}: beyond evaluation",
                linestyle=":", marker="x")
    ax.set(xlabel="added one-way delay (ms)", ylabel="seconds per iteration, n = 6 LM",
           title="Latency sweep: round trips per invocation = slope / 2")
    ax.legend(fontsize=8)
    _save(plt, fig, out, "latency.png")
    rows = [[side, f"{lat[side]['round_trips']:.2f}",
             f"{lat[side]['round_trips_beyond_evaluate']:.2f}",
             " / ".join(f"{v:.3f}" for v in lat[side]["per_iteration_s"])]
            for side in ("server", "client")]
    tcp = lat.get("tcp", {})
    return (f"## Latency sweep (n = 6 LM, TCP {tcp.get('congestion_control')}, slow start "
            f"after idle {tcp.get('slow_start_after_idle')})\n\n![](latency.png)\n\n"
            + _table(["delayed link", "round trips (wall)", "round trips (beyond evaluation)",
                      "s/iteration at " + " / ".join(f"{d:g}" for d in delays) + " ms"],
                     rows))


PROFILE_MARKERS = {"lan": ("o", "C0"), "paper": ("s", "C1"), "region": ("^", "C2"),
                   "continent": ("D", "C3")}


def _profiles(plt, results: dict, out: Path) -> str:
    """Wall time of a padded localization per network profile against its links' bound
    (``snail-bench netem --profile NAME --localize``)."""
    prof = results.get("profiles", {})
    names = [name for name in PROFILE_MARKERS if name in prof]
    if not names:
        return f"## Network profiles\n\nNot measured: {prof.get('lab', 'no lab')}"
    fig, ax = plt.subplots(figsize=(7, 4.5))
    rows, edges = [], []
    for name in names:
        marker, color = PROFILE_MARKERS[name]
        locs = sorted(prof[name]["localization"].items(), key=lambda kv: int(kv[0]))
        bounds = [loc["link_bound_s"] for _, loc in locs]
        walls = [loc["wall_s"] for _, loc in locs]
        edges += bounds + walls
        ax.plot(bounds, walls, linestyle="none", marker=marker, color=color,
                markerfacecolor="none", markersize=9, markeredgewidth=1.5, label=name)
        for (n, loc), x, y in zip(locs, bounds, walls):
            ax.annotate(f"n={n}", (x, y), textcoords="offset points", xytext=(6, 4),
                        fontsize=7, color=color)
            rows.append([name, n, str(loc["invocations"]),
                         f"{loc['bytes']['garbler_to_evaluator'] / 1e6:.1f}",
                         f"{loc['link_bound_s']:.3f}", f"{loc['wall_s']:.3f}",
                         f"{loc['bound_ratio']:.2f}"])
    lo, hi = min(edges) / 1.5, max(edges) * 1.5
    ax.plot([lo, hi], [lo, hi], color="0.4", linewidth=1, label="the links' bound")
    ax.plot([lo, hi], [1.3 * lo, 1.3 * hi], color="0.4", linewidth=1, linestyle="--",
            label="1.3 x the bound")
    ax.set(xscale="log", yscale="log", xlabel="bound set by the links alone (s, log)",
           ylabel="padded localization, wall (s, log)",
           title="One localization (20 invocations, LM) per network profile")
    ax.legend(fontsize=8)
    _save(plt, fig, out, "profiles.png")
    return ("## Network profiles: a localization against its links' bound\n\n"
            "![](profiles.png)\n\nThe bound is max(garbler -> evaluator bytes / the "
            "measured server rate, invocations x the measured client round trip).\n\n"
            + _table(["profile", "n", "invocations", "MB garbler->evaluator", "bound (s)",
                      "wall (s)", "wall / bound"], rows))
