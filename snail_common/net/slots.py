"""Session slots: how a daemon's ``--max-sessions`` and per-client quotas count live runs
and reservations.

A client garbles sessions ahead of need (garble-ahead): such a *reservation* is a
convenience, worth holding only while it costs nobody else anything. A *live* session is
one a client needs now (an invocation waits for it). So:

- a reservation is admitted only while the daemon is below ``--max-sessions``, its client
  below ``--max-sessions-per-peer`` and below ``--max-ahead-per-peer`` reservations;
  otherwise it is refused as ``busy`` (the client keeps fewer ahead: its pool shrinks);
- a live session that meets a full daemon (or its client's full quota) takes the slot of
  a reservation: the client holding the most reservations loses its newest, which ends
  as ``evicted`` (its client is told and prepares another when it needs one). Only when
  no reservation is left to take is a live session refused as ``busy``;
- a reservation becomes live once it is put to use (the evaluator: its labels are all
  in) and is never evicted after that.

Slots are counted here, synchronously: an evicted reservation's slot is free the moment
it is chosen, whatever its session still has to do to end.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

from .errors import BUSY, ProtocolError


@dataclass(eq=False)
class Slot:
    """One admitted session's place: whose it is, whether it is (still) a reservation,
    and how its daemon ends it when its place is taken (``evict``)."""

    peer: str
    ahead: bool
    evict: Callable[[], None] | None = None
    started: float = field(default_factory=time.monotonic)
    held: bool = True


class Slots:
    """The slots of one daemon (see the module doc)."""

    def __init__(self, role: str, max_sessions: int, max_per_peer: int,
                 max_ahead_per_peer: int) -> None:
        self.role = role
        self.max_sessions = max_sessions
        self.max_per_peer = max_per_peer
        self.max_ahead_per_peer = max_ahead_per_peer
        self._held: list[Slot] = []
        self._per_peer: Counter[str] = Counter()
        self._ahead_per_peer: Counter[str] = Counter()

    @property
    def active(self) -> int:
        return len(self._held)

    @property
    def reservations(self) -> int:
        return sum(self._ahead_per_peer.values())

    def admit(self, peer: str, ahead: bool,
              evict: Callable[[], None] | None = None) -> Slot:
        """A slot for a new session of ``peer`` ("" while unknown: the garbler's half of
        an evaluator session that came first), or ProtocolError ``busy``."""
        if ahead:
            self._room_to_reserve(peer)
        else:
            self._room_for_live(peer)
        slot = Slot(peer, ahead, evict)
        self._held.append(slot)
        self._count(slot, 1)
        return slot

    def claim(self, slot: Slot, peer: str) -> None:
        """The session's client is now known (its half came second): count it against
        that client's quota, taking one of its own reservations if the quota is full."""
        if slot.peer == peer or not slot.held:
            return
        if peer and self._per_peer[peer] >= self.max_per_peer \
                and not self._evict(lambda s: s.peer == peer and s is not slot):
            raise ProtocolError(BUSY, self._peer_full(peer))
        self._count(slot, -1)
        slot.peer = peer
        self._count(slot, 1)

    def live(self, slot: Slot) -> None:
        """A reservation is in use now: it no longer yields its place."""
        if slot.ahead and slot.held:
            self._count(slot, -1)
            slot.ahead = False
            self._count(slot, 1)

    def release(self, slot: Slot) -> None:
        """The session ended (once; an evicted slot was released when chosen)."""
        if slot.held:
            slot.held = False
            self._held.remove(slot)
            self._count(slot, -1)

    # ---- the rules -----------------------------------------------------------------------
    def _room_to_reserve(self, peer: str) -> None:
        if self.active >= self.max_sessions:
            raise ProtocolError(BUSY, f"the {self.role} runs its maximum of "
                                      f"{self.max_sessions} sessions: no room to garble "
                                      f"ahead")
        if peer and self._per_peer[peer] >= self.max_per_peer:
            raise ProtocolError(BUSY, self._peer_full(peer))
        if peer and self._ahead_per_peer[peer] >= self.max_ahead_per_peer:
            raise ProtocolError(BUSY, f"{peer} holds its maximum of "
                                      f"{self.max_ahead_per_peer} sessions garbled ahead "
                                      f"on the {self.role} (--max-ahead-per-peer)")

    def _room_for_live(self, peer: str) -> None:
        if peer and self._per_peer[peer] >= self.max_per_peer \
                and not self._evict(lambda s: s.peer == peer):
            raise ProtocolError(BUSY, self._peer_full(peer))
        if self.active >= self.max_sessions and not self._evict(lambda s: True):
            raise ProtocolError(BUSY, f"the {self.role} runs its maximum of "
                                      f"{self.max_sessions} sessions, none of them a "
                                      f"reservation it could give up")

    def _evict(self, eligible: Callable[[Slot], bool]) -> bool:
        """Take the place of one eligible reservation: the newest of the client holding
        the most; False when there is none."""
        candidates = [s for s in self._held if s.ahead and eligible(s)]
        if not candidates:
            return False
        victim = max(candidates, key=lambda s: (self._ahead_per_peer[s.peer], s.started))
        self.release(victim)
        if victim.evict is not None:
            victim.evict()
        return True

    def _count(self, slot: Slot, step: int) -> None:
        for counter, counted in ((self._per_peer, True), (self._ahead_per_peer, slot.ahead)):
            if counted and slot.peer:
                counter[slot.peer] += step
                if counter[slot.peer] <= 0:
                    del counter[slot.peer]

    def _peer_full(self, peer: str) -> str:
        return (f"{peer} runs its maximum of {self.max_per_peer} sessions on the "
                f"{self.role} (--max-sessions-per-peer)")
