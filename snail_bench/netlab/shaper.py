"""Which shaper the lab uses, and the ``tc`` arguments of each.

A user's own experiment would shape a link with ``tc qdisc ... netem`` (delay, jitter,
loss and rate in the kernel), so the lab does too wherever the kernel has ``sch_netem``.
Where it does not (this machine's kernel), delay, jitter and loss come from the lab's own
forwarder (``wire.c``, ``wire.py``) and the rate from ``tbf``. The choice is made once
per lab by trying a netem qdisc in the lab's own wire namespace, and reported as
``"shaper"`` in the netem JSON, so a reader knows which one produced a figure.
"""

from __future__ import annotations

import subprocess

SHAPERS = ("auto", "netem", "forwarder")
TBF_LATENCY_MS = 100  # how long a packet may queue in the rate limiter before it drops
NETEM_LIMIT = 100_000  # packets netem may hold: a BDP of 1 Gbit/s x 100 ms in 1.5 kB packets


class ShaperUnavailable(Exception):
    """The shaper asked for cannot run here (the message says why)."""


def netem_probe(namespace: str) -> str | None:
    """None if a netem qdisc can be set in ``namespace`` (tried on its loopback and
    removed again), else the reason it cannot (tc's own words)."""
    proc = subprocess.run(("tc", "-n", namespace, "qdisc", "add", "dev", "lo", "root",
                           "netem", "delay", "0ms"), capture_output=True, text=True)
    if proc.returncode != 0:
        return proc.stderr.strip() or f"tc exit {proc.returncode}"
    subprocess.run(("tc", "-n", namespace, "qdisc", "del", "dev", "lo", "root"),
                   capture_output=True)
    return None


def choose(requested: str, netem_missing: str | None) -> str:
    """"netem" or "forwarder" for a lab asked for ``requested`` (auto: netem where the
    kernel has it) given why netem is missing (None: it is there)."""
    if requested not in SHAPERS:
        raise ValueError(f"shaper must be one of {', '.join(SHAPERS)}, got {requested!r}")
    if requested == "forwarder":
        return "forwarder"
    if netem_missing is None:
        return "netem"
    if requested == "netem":
        raise ShaperUnavailable(f"the kernel has no netem qdisc here ({netem_missing}); "
                                f"use --shaper forwarder or auto")
    return "forwarder"


def netem_args(delay_ms: float, jitter_ms: float, loss_pct: float,
               rate_mbit: float | None) -> list[str]:
    """``tc qdisc replace ... root`` arguments of a netem qdisc with this shaping, as a
    user's own tc-netem experiment would set it (jitter uniformly distributed, as the
    forwarder draws it)."""
    args = ["netem", "limit", str(NETEM_LIMIT), "delay", f"{delay_ms:g}ms"]
    if jitter_ms:
        args += [f"{jitter_ms:g}ms", "distribution", "uniform"]
    if loss_pct:
        args += ["loss", f"{loss_pct:g}%"]
    if rate_mbit is not None:
        args += ["rate", f"{rate_mbit:g}mbit"]
    return args


def tbf_args(rate_mbit: float) -> list[str]:
    """``tc qdisc replace ... root`` arguments of the token bucket that rates a link when
    the forwarder delays it: a burst of 4 ms of the rate, at least two GSO frames."""
    rate_bytes = rate_mbit * 1e6 / 8
    burst = max(int(rate_bytes / 250), 2 * 65536 + 1514)
    return ["tbf", "rate", f"{rate_mbit:g}mbit", "burst", str(burst),
            "latency", f"{TBF_LATENCY_MS}ms"]
