"""Which failed invocations the client runs again, and which replica it passes over.

An invocation is retried, with a fresh session (new secrets: nothing of the failed one is
reused), while ``--busy-wait`` lasts, when the failure says nothing about the request
itself: a server at its limit (``busy``), a reservation whose place a live session took
(``evicted``); and, where its role has another replica to turn to, one that is stopping
(``draining``), a replica lost mid-run (a broken link, or ``peer_lost`` from the server
that lost its peer), a timeout. Tampering, a bad request,
a circuit a server does not have, a forbidden address are final, except an evaluator
replica the garbler cannot find among its operator's names where the client knows others
(in a rolling update, a garbler replica started after that evaluator replica left DNS
while it drained refuses it: another replica serves). The replica at fault
is shunned for a while (replicas.ReplicaSet), so the retry lands elsewhere when another
replica answers. A result is counted once, when it decodes; a failed attempt counts
nothing but a retry.
"""

from __future__ import annotations

from collections.abc import Iterable

from snail_common.net.errors import BUSY, EVICTED, FORBIDDEN, PEER_LOST, RETRYABLE

from .links import ServiceError
from .replicas import ReplicaSet
from .sessions import Prepared


def retryable(exc: ServiceError, session: Prepared | None,
              sets: dict[str, ReplicaSet]) -> bool:
    """Whether another attempt may succeed: after ``busy`` or ``evicted`` always (the
    server is there, only full), after the other retryable failures when the role at
    fault has another replica to turn to (with a single one, the failure is reported as
    it happened)."""
    if exc.code in (BUSY, EVICTED):
        return True
    if _evaluator_unknown_to_garbler(exc, session):
        return sets["evaluator"].several()
    lost = exc.code in RETRYABLE or (
        exc.code is None and exc.link is not None and not exc.link.alive)
    return lost and any(s.several() for s in _at_fault(exc, session, sets))


def _evaluator_unknown_to_garbler(exc: ServiceError, session: Prepared | None) -> bool:
    """The garbler refused, without dialling it, the evaluator replica this session
    named (its ``field 'evaluator'`` refusal)."""
    return (exc.code == FORBIDDEN and session is not None and exc.link is session.garbler
            and "field 'evaluator'" in str(exc))


def _at_fault(exc: ServiceError, session: Prepared | None,
              sets: dict[str, ReplicaSet]) -> list[ReplicaSet]:
    """The roles a failure points at (all of them when it names no link)."""
    if session is not None and exc.code == PEER_LOST and exc.link is session.garbler:
        return [sets["evaluator"], sets["garbler"]]  # the garbler lost its evaluator
    owners = [s for s in sets.values() if exc.link in s.links.values()]
    return owners or list(sets.values())


def blame(exc: ServiceError, session: Prepared | None, sets: Iterable[ReplicaSet]) -> None:
    """Shun the replicas this failure points at: a dead link's, the one that refused or
    failed the session, and the evaluator a garbler says it lost or does not know."""
    if _evaluator_unknown_to_garbler(exc, session):
        suspects = [session.evaluator]  # the garbler is fine: it only did not know it
    else:
        suspects = [exc.link] if exc.link is not None else []
    if session is not None:
        suspects += [link for link in (session.garbler, session.evaluator) if not link.alive]
        if exc.code == PEER_LOST and exc.link is session.garbler:
            suspects.append(session.evaluator)
    for replicas in sets:
        for link in suspects:
            replicas.shun_link(link)
