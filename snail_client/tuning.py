"""What a runner learns from its own runs: how deep to garble ahead and, with the
``auto`` scheme, which garbling scheme each circuit's next session asks for.

Both come from the garbler's measured rates (its stats of each run) and this client's
cycle on a circuit (its wall time, evaluation and waits): snail_common.net.linkrates.
"""

from __future__ import annotations

import math

from snail_common.net.linkrates import AUTO, Cycle, ahead_depth, deeper, pick_scheme

from .ahead import AheadPool
from .sessions import Prepared


class RunTuning:
    """A runner's garble-ahead depth (kept in ``pool``, never below ``floor``) and its
    sessions' schemes (``scheme``, or per circuit with ``auto``)."""

    def __init__(self, scheme: str, pool: AheadPool, floor: int) -> None:
        self.scheme, self.pool, self.floor = scheme, pool, floor
        self.measured: dict[str, float] = {}  # the garbler's last rates (its stats)
        self.cycles: dict[str, Cycle] = {}  # this client's own, per circuit id
        self.schemes: dict[str, str] = {}  # the scheme of each circuit's last run

    def measured_run(self, report: dict[str, float], session: Prepared, table_bytes: int,
                     wall: float, waited: float) -> None:
        """Take the garbler's rates from a session's stats; size the garble-ahead depth
        from them (its tables at the evaluator before they are asked for), one deeper
        where the evaluation of a session garbled ahead still ``waited`` for tables."""
        self.measured.update({k: v for k, v in report.items()
                              if k.startswith(("and_per_s_", "link_"))})
        delay = self.measured.get("link_rtt_ms", 0.0) / 2000  # the table stream's link
        if self.floor > 0:  # it only grows: one slow invocation (a busy core) must not
            # take away the depth the next ones need
            self.pool.ahead = max(deeper(self.pool.ahead, waited, delay), self.floor,
                                  ahead_depth(self.measured, session.iface.counts["and"],
                                              session.scheme, table_bytes, wall))

    def cycled(self, session: Prepared, timing: dict[str, float], wall: float) -> None:
        """Take this invocation into the client's cycle on its circuit (what ``auto``
        weighs a scheme's fewer bytes against)."""
        circuit_id = session.circuit_id
        self.schemes[circuit_id] = session.scheme
        if "evaluate_s" in timing:
            cycle = self.cycles.setdefault(circuit_id, Cycle(session.iface.counts["and"]))
            cycle.invoked(session.scheme, wall, float(timing["evaluate_s"]),
                          float(timing.get("wait_s", 0.0)),
                          float(timing.get("ahead_s", math.inf)))

    def next_scheme(self, circuit_id: str) -> str:
        """The scheme of the next session of ``circuit_id``: the runner's, or with
        ``auto`` the one the garbler's last measurements and this client's cycle on the
        circuit favour."""
        if self.scheme != AUTO:
            return self.scheme
        return pick_scheme(self.measured, self.cycles.get(circuit_id),
                           self.schemes.get(circuit_id, "halfgates"))
