"""The figure of ``snail-bench track``: per-frame latency and the RMS ratio to OpenCV's
converged pose along the sequence, one pair of panels per circuit, one PNG. Lost frames
are marked; the first frame (the padded localization) is off the latency axis's scale
and named in the title. Needs matplotlib (the ``bench`` extra)."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # after choosing the file-only backend


def draw(report: dict, path: Path) -> Path:
    """Write the figure of a ``{"track": ...}`` report (with its ``per_frame`` rows)."""
    entries = report["track"]
    fig, axes = plt.subplots(2, len(entries), figsize=(6 * len(entries), 5.5), sharex="col",
                             squeeze=False)
    for col, (name, entry) in enumerate(entries.items()):
        rows = entry["per_frame"]
        frames = [r["frame"] for r in rows]
        ms = [1000 * r["latency_s"] for r in rows]
        top, bottom = axes[0][col], axes[1][col]
        top.plot(frames[1:], ms[1:], lw=0.8, color="tab:blue")
        top.axhline(1000 * entry["latency_s"]["p95"], ls="--", lw=0.8, color="tab:red",
                    label=f"p95 {1000 * entry['latency_s']['p95']:.1f} ms")
        top.set_ylabel("latency, frame in to pose out (ms)")
        top.set_ylim(bottom=0)
        top.legend(fontsize=8, loc="upper right")
        top.set_title(f"{name}: {entry['sequence']}, {entry['setting']}, "
                      f"{entry['runs_per_frame']} run(s) a frame, {entry['fps']:.1f} frames/s"
                      f"\nfirst frame (padded, {entry['runs_first_frame']} runs) "
                      f"{ms[0]:.0f} ms", fontsize=9)
        ratios = [r["rms_ratio"] if r["rms_ratio"] is not None else math.nan for r in rows]
        bottom.plot(frames, ratios, lw=0.8, color="tab:green")
        bottom.axhline(1.01, ls="--", lw=0.8, color="tab:gray", label="OpenCV + 1 %")
        lost = [f for f, r in zip(frames, rows) if r["track_status"] == "lost"]
        if lost:
            bottom.plot(lost, [1.0] * len(lost), "rx", ms=4, label="lost")
        bottom.set_ylabel("RMS / OpenCV's converged RMS")
        bottom.set_xlabel("frame")
        bottom.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
