"""Which side bounds a session, the garbler's CPU or the server link, and the scheme that
follows (DESIGN.md round 3: half-gates where the garbler's CPU is the limit, three-halves
where the link is).

The garbler measures both on its own sessions: its garbling rate per scheme (AND gates
per CPU second of the thread that garbled them) and the table stream's delivery rate and
round trip (``tcpinfo``: the kernel's samples; the rate is the median of the recent
ones, each a stream's plus those of the streams sending beside it). It reports them in each
session's ``stats``; a client asking for ``auto`` picks the scheme of its next session
from them and from its own cycle (``pick_scheme``), and every client sizes its
garble-ahead depth from them (``ahead_depth``, ``deeper``).
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

from snail_common.gc.stream import SCHEME_HALF_GATES, SCHEME_THREE_HALVES, scheme_id, table_words

from .tcpinfo import TcpInfo

AUTO = "auto"  # the client's default: the scheme picked per session from the measurements
CLIENT_SCHEMES = (AUTO, "halfgates", "threehalves")
EWMA = 0.3  # weight of the newest sample
# an evaluation that waited longer than this for the tables of a session garbled ahead
WAIT_DEEPER_S = 0.002
WAITS_SEEN = 6  # the invocations whose waits for tables auto weighs
WAITS_MIN = 3  # ... at least this many of them
LATE_SHARE = 0.2  # waiting more than this share of their time: the tables set the pace
COLD_AHEAD_S = 0.01  # a session the evaluator had for less than this was not ahead
RATE_WINDOW = 10  # the table stream's rate is the median of this many sessions' samples
# three-halves garbles at about this share of half-gates' rate on one core, per garbling
# engine (numpy, README: 3.0 vs 7.9 M AND/s on wide steps; the native kernel, `snail-bench
# engine` 2026-11-27 10:16, load 1.4: 23.1 vs 38.1 M AND/s, half-gates on VAES); used
# until the garbler has measured both
SHARE_BY_ENGINE = {"numpy": 0.38, "native": 0.6}
THREE_HALVES_SHARE = SHARE_BY_ENGINE["numpy"]  # a client's guess: it cannot see the engine


def bytes_per_and(scheme: int) -> float:
    """Table bytes per AND gate in the stream (three-halves pads its control bits)."""
    return 8 * table_words(scheme, 1 << 13) / (1 << 13)


def _blend(old: float | None, new: float) -> float:
    return new if old is None else (1 - EWMA) * old + EWMA * new


@dataclass
class LinkRates:
    """The garbler's running estimates: AND/s per scheme, the link's rate (bytes/s) and
    round trip (s)."""

    and_per_s: dict[int, float] = field(default_factory=dict)
    rtt_s: float | None = None
    share: float = THREE_HALVES_SHARE  # the serving engine's (SHARE_BY_ENGINE)
    # the table streams' last delivery-rate samples (bytes/s) taken while the link held
    # them back, and those taken while the garbler had nothing to send (app-limited)
    rate_samples: deque[float] = field(default_factory=lambda: deque(maxlen=RATE_WINDOW))
    bounds: deque[float] = field(default_factory=lambda: deque(maxlen=RATE_WINDOW))

    @property
    def link_rate(self) -> float | None:
        """The link's rate: the median of the last RATE_WINDOW samples. One stream's
        sample is its share of the link (garble-ahead streams several sessions at once
        when the link is their limit: three at a time read a 50 Mbit/s link as 11), so
        each adds the shares of the streams sending beside it (``streamed``); the median
        keeps both the tails that understate a link and the bursts that overstate it
        out. App-limited samples only bound the rate below, and a shaper lets a burst
        through after an idle spell (three-halves at n = 256 over 2.5 Gbit/s read 4-9
        Gbit/s when such samples could raise the estimate): they stand in only while no
        stream has met the link."""
        samples = self.rate_samples or self.bounds
        return statistics.median(samples) if samples else None

    @classmethod
    def for_engine(cls, engine: str) -> LinkRates:
        """Estimates for a garbler serving with ``engine`` ("native" or "numpy")."""
        return cls(share=SHARE_BY_ENGINE[engine])

    def garbled(self, scheme: int, n_and: int, cpu_s: float) -> None:
        """A session of ``n_and`` AND gates took ``cpu_s`` of garbling threads' CPU."""
        if n_and > 0 and cpu_s > 0:
            self.and_per_s[scheme] = _blend(self.and_per_s.get(scheme), n_and / cpu_s)

    def streamed(self, info: TcpInfo | None, others: Sequence[TcpInfo | None] = ()) -> None:
        """The table stream's connection after a session, and the ``others`` streaming
        to the same evaluator at that moment: its smoothed round trip, blended (a minimum
        kept forever would hold a link that got slower, or a stream that moved to a
        farther replica, to the old round trip and keep the garble-ahead too shallow),
        and a sample of the link: its delivery rate plus those of the others sending now
        (tables in flight, their last sample not app-limited: one that is garbling its
        next frame does not share the link, whatever its last sample says)."""
        if info is None:
            return
        rtt = info.rtt_s or info.min_rtt_s  # smoothed: what the tables meet now
        if rtt:
            self.rtt_s = _blend(self.rtt_s, rtt)
        if not info.delivery_rate:
            return
        sample = float(info.delivery_rate) + sum(
            float(o.delivery_rate) for o in others
            if o is not None and o.delivery_rate and o.unacked and not o.app_limited)
        (self.bounds if info.app_limited else self.rate_samples).append(sample)

    def rate_of(self, scheme: int) -> float | None:
        """AND/s garbling ``scheme``: measured, or derived from the other scheme's."""
        if scheme in self.and_per_s:
            return self.and_per_s[scheme]
        if scheme == SCHEME_THREE_HALVES and SCHEME_HALF_GATES in self.and_per_s:
            return self.and_per_s[SCHEME_HALF_GATES] * self.share
        if scheme == SCHEME_HALF_GATES and SCHEME_THREE_HALVES in self.and_per_s:
            return self.and_per_s[SCHEME_THREE_HALVES] / self.share
        return None

    def report(self) -> dict[str, float]:
        """The estimates as ``stats`` timing fields (those known)."""
        out: dict[str, float] = {}
        for scheme, name in ((SCHEME_HALF_GATES, "halfgates"),
                             (SCHEME_THREE_HALVES, "threehalves")):
            rate = self.rate_of(scheme)
            if rate:
                out[f"and_per_s_{name}"] = round(rate)
        if self.link_rate:
            out["link_mbit"] = round(self.link_rate * 8 / 1e6, 1)
        if self.rtt_s:
            out["link_rtt_ms"] = round(self.rtt_s * 1000, 3)
        return out


def seconds_per_and(scheme: int, and_per_s: float, link_bytes_per_s: float) -> float:
    """A session's pace per AND gate: the slower of garbling and sending its tables."""
    return max(1 / and_per_s, bytes_per_and(scheme) / link_bytes_per_s)


@dataclass
class Cycle:
    """A client's own measure of its invocations of one circuit (``n_and`` AND gates):
    the seconds of each that were not the evaluation (its round trip, the transfer of
    its labels and outputs, its own work) and, per scheme, the evaluation's own seconds
    (without its waits for tables). Blended like the garbler's rates."""

    n_and: int
    other_s: float | None = None
    evaluate_s: dict[str, float] = field(default_factory=dict)
    # (wall, wait for tables) of the last invocations whose sessions were garbled ahead
    waits: deque[tuple[float, float]] = field(
        default_factory=lambda: deque(maxlen=WAITS_SEEN))

    def invoked(self, scheme: str, wall_s: float, evaluate_s: float, wait_s: float,
                ahead_s: float = math.inf) -> None:
        """An invocation in ``scheme`` took ``wall_s``; the evaluator spent ``evaluate_s``
        from the client's labels to its result, ``wait_s`` of it waiting for tables, and
        had the session ``ahead_s`` before the labels came."""
        self.other_s = _blend(self.other_s, max(wall_s - evaluate_s, 0.0))
        self.evaluate_s[scheme] = _blend(self.evaluate_s.get(scheme),
                                         max(evaluate_s - wait_s, 0.0))
        if ahead_s >= COLD_AHEAD_S:  # a session asked for just now waits whatever the link
            self.waits.append((wall_s, wait_s))

    @property
    def tables_late(self) -> bool:
        """The recent invocations spent more than LATE_SHARE of their time waiting for
        tables: the link (or the garbler) sets the pace, not the client's cycle. Sessions
        streamed side by side arrive in bunches, so one invocation waits for several and
        the next ones for none: the share, not each wait, tells."""
        if len(self.waits) < WAITS_MIN:
            return False
        return sum(w for _, w in self.waits) > LATE_SHARE * sum(t for t, _ in self.waits)


# the other scheme must promise a session this much shorter before auto switches to it:
# closer predictions say only that both run at one pace, and flipping on noise would
# cost the garble-ahead sessions of the scheme left
SWITCH_GAIN = 0.1


def _garbled_and_sent(scheme: str, n_and: int, rates: dict[str, float],
                      link_bytes_per_s: float) -> float:
    """Seconds to garble ``n_and`` AND gates in ``scheme`` and send their tables."""
    return n_and * seconds_per_and(scheme_id(scheme), rates[scheme], link_bytes_per_s)


def session_seconds(scheme: str, rates: dict[str, float], link_bytes_per_s: float,
                    cycle: Cycle | None) -> float:
    """A session's predicted pace in ``scheme``: the slowest of garbling it, sending its
    tables, and (once ``cycle`` has measured it) the client's cycle around it; per AND
    gate while the circuit is unknown. ``rates``: AND/s garbling each scheme."""
    pace = _garbled_and_sent(scheme, cycle.n_and if cycle is not None else 1, rates,
                             link_bytes_per_s)
    if cycle is None or cycle.other_s is None or not cycle.evaluate_s:
        return pace
    if scheme in cycle.evaluate_s:
        evaluation = cycle.evaluate_s[scheme]
    else:  # evaluation costs as garbling does, relative to the other scheme's
        measured, seconds = next(iter(cycle.evaluate_s.items()))
        evaluation = seconds * rates[measured] / rates[scheme]
    return max(pace, cycle.other_s + evaluation)


def pick_scheme(report: dict[str, float] | None, cycle: Cycle | None = None,
                current: str = "halfgates") -> str:
    """The scheme a session should use given the garbler's last ``report`` (its stats
    timing fields, as ``LinkRates.report`` writes them) and the client's ``cycle`` on
    this circuit: the ``current`` one unless the other promises a session at least
    SWITCH_GAIN shorter. Three-halves' fewer bytes win where the link, not the garbler
    nor the client's own round trip, sets the pace; half-gates is left only once the
    evaluations have been waiting for tables (the link's rate, one stream's samples,
    is too rough to decide on alone), on the link's word alone until three-halves has
    run on the circuit. Half-gates while nothing is measured."""
    if not report or "link_mbit" not in report or "and_per_s_halfgates" not in report:
        return "halfgates"
    link = report["link_mbit"] * 1e6 / 8
    rates = {"halfgates": report["and_per_s_halfgates"],
             "threehalves": report.get("and_per_s_threehalves",
                                       report["and_per_s_halfgates"] * THREE_HALVES_SHARE)}
    other = "threehalves" if current == "halfgates" else "halfgates"
    if current == "halfgates" and cycle is not None and cycle.other_s is not None:
        if not cycle.tables_late:
            return current  # tables in time: fewer bytes cannot make a session sooner
        pace = {s: _garbled_and_sent(s, cycle.n_and, rates, link) for s in rates}
        own = cycle.other_s + cycle.evaluate_s.get(current, 0.0)
        if other not in cycle.evaluate_s and pace[current] > own \
                and pace[other] < (1 - SWITCH_GAIN) * pace[current]:
            # never run on this circuit, where the link (not the client's own cycle)
            # sets the pace: its evaluation cannot be told from half-gates' (at n = 256
            # over 2.5 Gbit/s it was mostly the tables' bytes, not the hashes the
            # garbling rates compare), so the link and the garbler decide, and its own
            # sessions then measure it
            return other
    if session_seconds(other, rates, link, cycle) \
            < (1 - SWITCH_GAIN) * session_seconds(current, rates, link, cycle):
        return other
    return current


MAX_AHEAD = 3  # sessions garbled ahead at most: each holds a stream and evaluator memory


def ahead_depth(report: dict[str, float], n_and: int, scheme: str, table_bytes: int,
                interval_s: float, most: int = MAX_AHEAD) -> int:
    """Sessions to keep garbled ahead so that the next one's tables are all at the
    evaluator when it is invoked: a session asked for now is needed ``depth``
    invocations (of ``interval_s`` each) later, and takes its garbling at the
    garbler's own rate, its ``table_bytes`` over the link's rate and the link's one-way
    delay to get there (the bandwidth-delay product in time). 1 while nothing is
    measured; at most ``most``."""
    rate = report.get(f"and_per_s_{scheme}")
    if not rate or interval_s <= 0:
        return 1
    lag = n_and / rate + report.get("link_rtt_ms", 0.0) / 2000
    if report.get("link_mbit"):
        lag += table_bytes * 8 / (report["link_mbit"] * 1e6)
    return max(1, min(most, math.ceil(lag / interval_s)))


def deeper(depth: int, waited_s: float, link_delay_s: float, most: int = MAX_AHEAD) -> int:
    """The garble-ahead depth after an evaluation of a session garbled ahead waited
    ``waited_s`` for its tables: one more where it waited on a link whose one-way delay
    (``link_delay_s``) is long enough to be why. A window-limited stream on a long link
    brings the tables later than the measured rate and delay say, so the estimate alone
    keeps the depth too shallow. On a short link a wait means busy servers (many clients
    on one pair): sessions asked for earlier wait behind the same cores, and each one
    more holds a stream and evaluator memory."""
    if waited_s > WAIT_DEEPER_S and link_delay_s > WAIT_DEEPER_S and depth < most:
        return depth + 1
    return depth
