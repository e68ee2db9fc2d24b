"""The report of ``snail-bench soak`` (``soak.py`` runs it): what one run does, what the
clients and the sampler saw, and the arithmetic that turns that into the report. Pure: no
processes or daemons, so it is unit-tested on synthetic samples.

The report gives per minute the largest sample, the invocations and their latency
percentiles, and a verdict: ``flat`` when, for every daemon, RSS and open fds once the
clients have left are within 10 % of what they were at rest before the fleet
(``idle_before``), and, in a run of three minutes or more, the last minute's peaks are
within 10 % of the second's (the first holds start-up and warm caches). ``ok`` asks for
no wrong result, no failure of any kind (busy included: a live run must never find the
servers full of other clients' reservations) and the descriptors back.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from snail_common.net.errors import BUSY

ROLES = ("garbler", "evaluator")
ALGORITHMS = ("lm", "gn")
EXPLAINED = (BUSY,)  # a server at its session limit, still busy after the client's wait
FLAT_TOLERANCE = 0.10  # last minute within this fraction of the second; after vs before
SAMPLE_S = 2.0
EXAMPLES_KEPT = 5  # wrong results and failure messages quoted in the report


@dataclass(frozen=True)
class Plan:
    """What one soak run does."""

    clients: int
    minutes: float
    points: tuple[int, ...] = (6, 12)
    algorithms: tuple[str, ...] = ALGORITHMS
    min_invocations: int = 20
    sample_s: float = SAMPLE_S
    kill_every_s: float | None = None  # a random client is killed (SIGKILL) this often

    @property
    def buckets(self) -> int:
        """Minutes in the report: a started minute counts (0.3 minutes is one)."""
        return max(1, math.ceil(self.minutes - 1e-9))


@dataclass(frozen=True)
class Sample:
    """One look at a daemon: its footprint from /proc and, from its health message, the
    sessions under way and the garbled-table bytes it buffers ahead of labels (None when
    the health request failed)."""

    t: float
    role: str
    rss_mb: float
    fds: int
    sessions: int | None = None
    queued_mb: float | None = None


@dataclass
class Tally:
    """Everything the clients and the sampler reported, with times since the start."""

    invocations: list[tuple[float, float]] = field(default_factory=list)  # (t, latency s)
    frames: int = 0
    wrong: list[dict] = field(default_factory=list)
    failures: Counter = field(default_factory=Counter)
    failure_examples: list[str] = field(default_factory=list)
    samples: list[Sample] = field(default_factory=list)
    killed_clients: int = 0  # by the soak (--kill-clients): their frames are not failures


# ---- arithmetic over samples ------------------------------------------------------------

def percentiles(values: list[float]) -> dict[str, float | None]:
    """p50, p95 and p99 (linear interpolation), None for no values."""
    if not values:
        return {"p50": None, "p95": None, "p99": None}
    p = np.percentile(np.asarray(values, float), [50, 95, 99])
    return {"p50": round(float(p[0]), 4), "p95": round(float(p[1]), 4),
            "p99": round(float(p[2]), 4)}


def minute_of(t: float, buckets: int) -> int:
    """The minute a time (seconds since the start) falls in; a frame that finishes after
    the end counts in the last minute, anything before the start in the first."""
    return min(max(int(t // 60), 0), buckets - 1)


def bucket(timed: list[tuple[float, float]], buckets: int) -> list[list[float]]:
    """Values of (t, value) pairs grouped by minute."""
    out: list[list[float]] = [[] for _ in range(buckets)]
    for t, value in timed:
        out[minute_of(t, buckets)].append(value)
    return out


def per_minute_max(timed: list[tuple[float, float]], buckets: int) -> list[float | None]:
    """Largest value per minute (a leak shows in the peaks), None for a minute without
    samples."""
    return [max(values) if values else None for values in bucket(timed, buckets)]


def within(value: float, base: float, tolerance: float = FLAT_TOLERANCE) -> bool:
    """Whether ``value`` is within ``tolerance`` of ``base`` (a count or a size)."""
    return abs(value - base) <= tolerance * base


def flat(series: list[float | None], tolerance: float = FLAT_TOLERANCE) -> bool | None:
    """True when the last minute is within ``tolerance`` of the second; None when there
    is no third minute (the second would be compared with itself) or a sample is missing."""
    if len(series) < 3 or series[1] is None or series[-1] is None:
        return None
    return abs(series[-1] - series[1]) <= tolerance * series[1]


# ---- the daemons' logs and the report ---------------------------------------------------

def daemon_log(path: Path) -> dict:
    """What a daemon's JSON log says about the run: sessions by outcome, and warnings and
    errors by event (the operator's view, beside the clients')."""
    sessions: Counter = Counter()
    troubles: Counter = Counter()
    for line in path.read_text(errors="replace").splitlines():
        try:
            entry = json.loads(line)
        except ValueError:
            troubles["unparsed_line"] += 1
            continue
        if not isinstance(entry, dict):
            continue
        if entry.get("event") == "session":
            sessions[str(entry.get("outcome"))] += 1
        elif entry.get("level") in ("warning", "error", "critical"):
            troubles[f"{entry.get('level')}:{entry.get('event')}"] += 1
    return {"sessions": dict(sessions), "warnings": dict(troubles)}


def summarize(tally: Tally, plan: Plan, elapsed: float, before: dict, after: dict) -> dict:
    """The report: FORMATS' fields (invocations, wrong, failures, latency_s, rss_mb, fds,
    idle_before, killed_clients) and per-minute series, the flatness verdict (``before``:
    each daemon's fds and RSS at rest before the fleet, ``after``: its state once the
    clients left) and what is needed to reproduce a wrong frame. Clients finish the
    frame under way at the end (so it can be checked): that wind-down, with ever fewer
    clients, is left out of the invocation counts, latencies and per-minute values and
    reported apart; its frames are still checked and its failures counted, and the raw
    samples cover it."""
    buckets, window = plan.buckets, plan.minutes * 60
    inside = [(t, latency) for t, latency in tally.invocations if t < window]
    per_minute = bucket(inside, buckets)
    during = [sample for sample in tally.samples if sample.t < window]

    def series(what: str) -> dict[str, list]:
        return {role: per_minute_max([(x.t, getattr(x, what)) for x in during
                                      if x.role == role and getattr(x, what) is not None],
                                     buckets) for role in ROLES}

    rss, fds = series("rss_mb"), series("fds")
    verdicts = {f"{what}/{role}": flat(series[role])
                for what, series in (("rss_mb", rss), ("fds", fds)) for role in ROLES}
    verdicts.update({f"after/{what}/{role}": after[role][what] is not None
                     and within(after[role][what], before[role][what])
                     for what in ("rss_mb", "fds") for role in ROLES})
    overall = all(v for v in verdicts.values() if v is not None)
    unexplained = sum(n for kind, n in tally.failures.items() if kind not in EXPLAINED)
    minute_latency = [percentiles(values) for values in per_minute]
    return {"soak": {
        "clients": plan.clients, "minutes": plan.minutes, "elapsed_s": round(elapsed, 1),
        "points": list(plan.points), "algorithms": list(plan.algorithms),
        "min_invocations": plan.min_invocations,
        "invocations": len(inside), "frames": tally.frames,
        "wind_down": {"seconds": round(max(elapsed - window, 0.0), 1),
                      "invocations": len(tally.invocations) - len(inside)},
        "wrong": len(tally.wrong), "failures": dict(tally.failures),
        "unexplained_failures": unexplained, "killed_clients": tally.killed_clients,
        "kill_every_s": plan.kill_every_s,
        "latency_s": percentiles([latency for _, latency in inside]),
        "rss_mb": rss, "fds": fds,
        "invocations_per_minute": [len(values) for values in per_minute],
        "latency_per_minute_s": {p: [row[p] for row in minute_latency]
                                 for p in ("p50", "p95", "p99")},
        "flat": overall, "flat_by_series": verdicts, "idle_before": before,
        "after_clients_left": after,
        "sessions": series("sessions"), "queued_mb": series("queued_mb"),
        "samples": {role: [[round(x.t, 1), x.rss_mb, x.fds, x.sessions, x.queued_mb]
                           for x in tally.samples if x.role == role]
                    for role in ROLES},  # [t_s, rss_mb, fds, sessions, queued_mb]
        "wrong_examples": tally.wrong[:EXAMPLES_KEPT],
        "failure_examples": tally.failure_examples[:EXAMPLES_KEPT],
        "ok": not tally.wrong and not tally.failures and bool(after.get("fds_back")),
    }}
