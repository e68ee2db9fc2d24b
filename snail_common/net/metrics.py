"""A daemon's counters, kept once and read three ways: the ``health`` message, the
per-session JSON log line and the Prometheus text served on ``--metrics``.

Gauges say what is under way now (sessions, streams, connections, buffered bytes);
counters only grow (sessions by outcome, bytes, AND gates, seconds, refusals), so a
scraper can turn them into rates.
"""

from __future__ import annotations

import os
import resource
import sys
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

# sessions refused for lack of a slot, or by a draining daemon, and reservations given up
# for a live session: not counted as failed
from .errors import BUSY, DRAINING, EVICTED

OK = "ok"
# kept up to date by the daemon; ``reserved``: of the active, those garbled ahead (slots.py)
GAUGES = ("active", "reserved", "streaming", "queued_bytes")
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


@dataclass
class Metrics:
    """Everything an operator can ask a daemon about its load."""

    role: str
    connections: Callable[[], int]  # read when asked: a count the daemon already keeps
    gauges: dict[str, int] = field(default_factory=lambda: dict.fromkeys(GAUGES, 0))
    sessions: Counter = field(default_factory=Counter)  # outcome -> sessions ended so
    refused: Counter = field(default_factory=Counter)  # reason -> connections refused
    bytes_in: int = 0
    bytes_out: int = 0
    and_gates: int = 0
    session_seconds: float = 0.0

    def session_ended(self, outcome: str, and_gates: int, bytes_in: int, bytes_out: int,
                      seconds: float) -> None:
        self.sessions[outcome] += 1
        self.and_gates += and_gates if outcome == OK else 0
        self.bytes_in += bytes_in
        self.bytes_out += bytes_out
        self.session_seconds += seconds

    def health(self) -> dict[str, int]:
        """The ``sessions`` field of the health message."""
        done, busy = self.sessions[OK], self.sessions[BUSY]
        draining, evicted = self.sessions[DRAINING], self.sessions[EVICTED]
        return {**self.gauges, "connections": self.connections(), "done": done,
                "failed": sum(self.sessions.values()) - done - busy - draining - evicted,
                "busy": busy, "draining": draining, "evicted": evicted,
                "rejected": sum(self.refused.values()), "rss_bytes": rss_bytes()}

    def prometheus(self) -> str:
        """The Prometheus text exposition format (version 0.0.4)."""
        role = f'role="{self.role}"'
        lines: list[str] = []

        def metric(name: str, kind: str, text: str,
                   samples: list[tuple[str, float]]) -> None:
            lines.extend([f"# HELP snail_{name} {text}", f"# TYPE snail_{name} {kind}"])
            lines.extend(f"snail_{name}{{{labels}}} {value:g}" for labels, value in samples)

        metric("sessions_active", "gauge", "Sessions under way.",
               [(role, self.gauges["active"])])
        metric("sessions_reserved", "gauge", "Sessions garbled ahead of their client's need.",
               [(role, self.gauges["reserved"])])
        metric("sessions_streaming", "gauge", "Sessions streaming garbled tables.",
               [(role, self.gauges["streaming"])])
        metric("connections", "gauge", "Open authenticated connections.",
               [(role, self.connections())])
        metric("queued_bytes", "gauge", "Garbled-table bytes buffered ahead of labels.",
               [(role, self.gauges["queued_bytes"])])
        metric("resident_memory_bytes", "gauge", "Resident set size of the daemon.",
               [(role, rss_bytes())])
        outcomes = sorted({OK, *self.sessions})
        metric("sessions_total", "counter", "Sessions ended, by outcome (ok or error code).",
               [(f'{role},outcome="{o}"', self.sessions[o]) for o in outcomes])
        metric("connections_refused_total", "counter", "Connections refused, by reason.",
               [(f'{role},reason="{r}"', n) for r, n in sorted(self.refused.items())]
               or [(f'{role},reason="tls"', 0)])
        metric("session_bytes_in_total", "counter", "Bytes received for sessions.",
               [(role, self.bytes_in)])
        metric("session_bytes_out_total", "counter", "Bytes sent for sessions.",
               [(role, self.bytes_out)])
        metric("and_gates_total", "counter", "AND gates of sessions that ended ok.",
               [(role, self.and_gates)])
        metric("session_seconds_total", "counter", "Wall seconds spent in sessions.",
               [(role, self.session_seconds)])
        return "\n".join(lines) + "\n"


def rss_bytes() -> int:
    """This process's resident memory now (Linux), else its peak."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * _PAGE
    except (OSError, ValueError, IndexError):
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return peak if sys.platform == "darwin" else peak * 1024
