"""The figure of ``snail-bench soak``: load held and footprint over time, one PNG.

Four panels sharing the time axis (minutes): invocations per minute, latency p50/p95 per
minute, each daemon's RSS (with the evaluator's garbled tables buffered ahead of labels,
which it holds by design up to --ahead-mb) and each daemon's open file descriptors and
sessions under way at every sample: a leak shows as a slope, a burst as a spike.
Needs matplotlib (the ``bench`` extra).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # after choosing the file-only backend

ROLE_STYLE = {"garbler": {"color": "tab:blue"}, "evaluator": {"color": "tab:orange"}}


def plot_soak(soak: dict, path: Path) -> Path:
    """Write the four-panel figure of a soak report's body to ``path`` (PNG)."""
    fig, axes = plt.subplots(2, 2, figsize=(9, 6), sharex=True)
    minutes = [i + 0.5 for i in range(len(soak["invocations_per_minute"]))]
    (ax_inv, ax_lat), (ax_rss, ax_fds) = axes

    ax_inv.bar(minutes, soak["invocations_per_minute"], width=0.8, color="tab:green")
    ax_inv.set_ylabel("invocations / minute")
    ax_inv.set_title(f"{soak['clients']} clients, n = "
                     f"{'/'.join(str(n) for n in soak['points'])}, "
                     f"{'/'.join(soak['algorithms'])}: {soak['invocations']} invocations, "
                     f"{soak['wrong']} wrong", fontsize=9)

    for p, style in (("p50", "-"), ("p95", "--")):
        values = soak["latency_per_minute_s"][p]
        ax_lat.plot(minutes, [_nan(v) for v in values],
                    linestyle=style, marker="o", color="tab:purple", label=p)
    ax_lat.set_ylabel("latency per invocation (s)")
    ax_lat.set_ylim(bottom=0)
    ax_lat.legend(fontsize=8)

    for role, rows in soak["samples"].items():  # [t_s, rss_mb, fds, sessions, queued_mb]
        t = [row[0] / 60 for row in rows]
        style = ROLE_STYLE.get(role, {})
        ax_rss.plot(t, [row[1] for row in rows], label=f"{role} RSS", **style)
        ax_fds.plot(t, [row[2] for row in rows], label=f"{role} fds", **style)
        ax_fds.plot(t, [_nan(row[3]) for row in rows], label=f"{role} sessions",
                    linestyle="--", linewidth=0.8, **style)
        if role == "evaluator":
            ax_rss.plot(t, [_nan(row[4]) for row in rows], label="evaluator tables ahead",
                        linestyle="--", linewidth=0.8, **style)
    for ax in (ax_rss, ax_fds):  # after this, clients only finish their last frame
        ax.axvline(soak["minutes"], color="grey", linestyle=":", label="end")
    after = soak.get("after_clients_left", {})
    t_after = (soak["elapsed_s"] + after.get("seconds", 0.0)) / 60
    for role, rest in soak.get("idle_before", {}).items():  # at rest, and once idle again
        style = ROLE_STYLE.get(role, {})
        for ax, what in ((ax_rss, "rss_mb"), (ax_fds, "fds")):
            ax.axhline(rest[what], linestyle=":", linewidth=0.8, **style)
            if after.get(role, {}).get(what) is not None:
                ax.plot([t_after], [after[role][what]], marker="o", markersize=4, **style)
    ax_rss.set_ylabel("MB")
    ax_rss.set_ylim(bottom=0)
    ax_fds.set_ylabel("open fds, sessions under way")
    ax_fds.set_ylim(bottom=0)
    verdict = {True: "flat", False: "NOT flat", None: "too short to judge"}[soak["flat"]]
    ax_rss.set_title(f"footprint: {verdict} (dotted: at rest before; dot: after the "
                     f"clients left; 10 %)", fontsize=9)
    for ax in (ax_rss, ax_fds):
        ax.set_xlabel("minutes")
        ax.legend(fontsize=7)
    for ax in axes.flat:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def _nan(value: float | None) -> float:
    return float("nan") if value is None else value
