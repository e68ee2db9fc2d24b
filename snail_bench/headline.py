"""The headline table of README.md and docs/performance.md, made from one ``snail-bench
paper`` run's results.json, so both always quote the same run with its date, commit and
machine (tests/test_docs_headline.py holds them to ``docs/paper/results.json``).

After ``snail-bench paper --out docs/paper``, ``python -m snail_bench.headline
docs/paper/results.json README.md docs/performance.md`` rewrites the table between the
``headline`` markers of both files (without files it prints the table).
``provenance()`` is what the paper run records about itself.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from pathlib import Path

from snail_common.gc.engine import engine_status

BEGIN, END = "<!-- headline:begin -->", "<!-- headline:end -->"


def provenance() -> dict:
    """The commit (with ``+dirty`` for uncommitted changes), the machine and the garbling
    engine of a run (the daemons it starts inherit the environment that chose it)."""
    repo = Path(__file__).resolve().parents[1]
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=repo,
                                capture_output=True, text=True, timeout=10,
                                check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=repo, capture_output=True, text=True, timeout=10).stdout
        commit += "+dirty" if dirty.strip() else ""
    except (OSError, subprocess.SubprocessError):
        commit = "unknown (not a git checkout)"
    return {"commit": commit, "machine": _machine(), "engine": _engine()}


def _engine() -> str:
    status = engine_status()
    if status["engine"] == "native":
        threads = int(status["threads"])
        return f"native kernel, {threads} thread{'' if threads == 1 else 's'} per run"
    return f"numpy ({status.get('reason', 'asked for')})"


def _machine() -> str:
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    memory = ""
    if hasattr(os, "sysconf") and "SC_PHYS_PAGES" in os.sysconf_names:
        memory = f", {os.sysconf('SC_PHYS_PAGES') * os.sysconf('SC_PAGE_SIZE') / 2**30:.0f} GiB"
    return f"{os.cpu_count()} cores, {model}{memory}, {platform.system()}"


def _at(series: list[dict], n: int, key: str) -> float | None:
    return next((row[key] for row in series if row["n"] == n), None)


def _paper_at(ref: dict, key: str, n: int) -> float | None:
    return ref[key][ref["n"].index(n)] if n in ref.get("n", []) and key in ref else None


def _span(values: list[float], unit: str) -> str:
    lo, hi = min(values), max(values)
    digits = 0 if lo >= 100 else 1
    return f"{lo:.{digits}f} {unit}" if lo == hi else f"{lo:.{digits}f}-{hi:.{digits}f} {unit}"


def _seconds(x: float) -> str:
    return f"{x:.3f} s" if x < 1 else f"{x:.2f} s"


def _bytes(x: float) -> str:
    if x >= 1e9:
        return f"{x / 1e9:.1f} GB"
    return f"{x / 1e6:.0f} MB" if x >= 1e8 else f"{x / 1e6:.1f} MB"


def rows(results: dict, paper: dict) -> list[tuple[str, str, str]]:
    """(figure, ours, paper's) for every headline the run measured."""
    out = []
    series = results.get("sweep", {}).get("series", {})
    ref0, ref5 = paper.get("emp_sil_0ms", {}), paper.get("emp_sil_5ms", {})
    for n in (6, 256):
        ours = _at(series.get("lm_0ms", []), n, "per_iteration_s")
        if ours is not None:
            theirs = _paper_at(ref0, "lm_s_per_iteration", n)
            out.append((f"one LM iteration, n = {n} points", _seconds(ours),
                        _seconds(theirs) if theirs else "-"))
    for n in (6, 256):
        ours = _at(series.get("lm_0ms", []), n, "bytes")
        if ours is not None:
            theirs = _paper_at(ref0, "lm_bytes_per_iteration", n)
            out.append((f"garbled tables per iteration, n = {n}", _bytes(ours),
                        _bytes(theirs) if theirs else "-"))
    ours = _at(series.get("lm_5ms", []), 6, "per_iteration_s")
    if ours is not None:
        theirs = _paper_at(ref5, "lm_s_per_iteration", 6)
        out.append(("one LM iteration, n = 6, 5 ms between the servers", _seconds(ours),
                    _seconds(theirs) if theirs else "-"))
    ref = paper.get("emp_do_vs_sil", {})
    for mode, key, name in (("sil", "lm_sil_total_s", "one LM localization"),
                            ("do", "lm_do_total_s", "one data-oblivious LM localization")):
        runs = [r for r in results.get("totals", {}).get(mode, {}).values()
                if r["algorithm"] == "lm"]
        if runs:
            ns = sorted(r["n"] for r in runs)
            theirs = [_paper_at(ref, key, n) for n in ns]
            out.append((f"{name}, n = {ns[0]}..{ns[-1]}",
                        _span([r["total_s"] for r in runs], "s"),
                        _span([t for t in theirs if t is not None], "s")
                        if any(t is not None for t in theirs) else "-"))
    latency = results.get("latency", {})
    if "client" in latency and "server" in latency:
        out.append(("round trips per invocation beyond evaluation: client links / server "
                    "link", f"{latency['client']['round_trips_beyond_evaluate']:.2f} / "
                    f"{latency['server']['round_trips_beyond_evaluate']:.2f}", "-"))
    return out


def headline(results: dict, paper: dict) -> str:
    """The Markdown table with its provenance line."""
    lines = [f"From one `snail-bench paper` run: {results.get('started', '?')} to "
             f"{results.get('finished', '?')}, commit {results.get('commit', 'unknown')}, "
             f"{results.get('machine', 'machine unknown')}; both servers and the client on it, "
             f"TLS on every link, {_links_phrase(results)}, the default circuits and "
             f"`--scheme auto`, {_engine_phrase(results)}. Paper: EMP-toolkit on a desktop "
             "CPU.",
             ""]
    latency = results.get("latency", {})
    if latency.get("commit"):
        lines[0] += (f" The latency sweep re-measured {latency.get('measured', '?')}, commit "
                     f"{latency['commit']}.")
    lines += ["| figure | snail | paper |", "|---|---:|---:|"]
    lines += [f"| {figure} | {ours} | {theirs} |" for figure, ours, theirs in rows(results,
                                                                                   paper)]
    return "\n".join(lines) + "\n"


def _links_phrase(results: dict) -> str:
    """Where the iteration rows ran: across the network lab's link between the servers
    (the paper's 2.5 Gbit/s) when the run could build it, else on loopback."""
    if isinstance(results.get("sweep", {}).get("lab"), dict):
        return ("iterations across the network lab's 2.5 Gbit/s link between the servers, "
                "localizations on loopback")
    return "loopback"


def _engine_phrase(results: dict) -> str:
    engine = results.get("engine")
    return f"engine: {engine}" if engine else "engine: numpy (before the native kernel)"


def between_markers(text: str) -> str | None:
    """What a document holds between the headline markers (None without them)."""
    if BEGIN not in text or END not in text:
        return None
    return text.split(BEGIN, 1)[1].split(END, 1)[0].strip("\n") + "\n"


def main(argv: list[str]) -> int:
    if not argv:
        print("usage: python -m snail_bench.headline RESULTS.json [DOCUMENT.md ...]",
              file=sys.stderr)
        return 2
    from .paper import PAPER_RESULTS

    results = json.loads(Path(argv[0]).read_text())
    table = headline(results, json.loads(PAPER_RESULTS.read_text()))
    if len(argv) == 1:
        sys.stdout.write(table)
    for document in map(Path, argv[1:]):
        text = document.read_text()
        if between_markers(text) is None:
            print(f"{document}: no {BEGIN} ... {END} block", file=sys.stderr)
            return 2
        before, rest = text.split(BEGIN, 1)
        document.write_text(f"{before}{BEGIN}\n{table}{END}{rest.split(END, 1)[1]}")
        print(f"{document}: headline from {argv[0]}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
