"""How a run's two answers become its result or its failure (sessions.collect_answers),
and what the garble-ahead pool does with a session the evaluator failed while it waited
(ahead.AheadPool.take), with fake servers: the client must report the evaluator's word
that the tables changed on the server link, not the garbler's word that it lost the
evaluator, nor pass over such a session in silence."""

from __future__ import annotations

import asyncio
from collections import deque
from types import SimpleNamespace

import numpy as np
import pytest

from snail_client import sessions
from snail_client.ahead import AheadPool
from snail_client.links import Inbox, ServiceError
from snail_common.net.errors import LINK, PEER_LOST


def _session() -> SimpleNamespace:
    return SimpleNamespace(iface=SimpleNamespace(n_outputs=4),
                           garbler=SimpleNamespace(where="the garbler at g:1"),
                           evaluator=SimpleNamespace(where="the evaluator at e:1"),
                           to_g=Inbox(), to_e=Inbox())


def _error(code: str, message: str) -> dict:
    return {"t": "error", "code": code, "message": message}


def _failure(session: SimpleNamespace) -> ServiceError:
    with pytest.raises(ServiceError) as info:
        asyncio.run(sessions.collect_answers(session))
    return info.value


def test_the_evaluators_word_that_the_tables_changed_beats_the_garblers_lost_link():
    async def run() -> ServiceError:
        session = _session()
        session.to_g.put(_error(PEER_LOST, "lost the evaluator: link closed"))
        # the evaluator's error comes after the garbler's, as it does when the garbler
        # hears the closed link first
        asyncio.get_running_loop().call_later(
            0.05, session.to_e.put, _error(LINK, "a table frame fails its seal"))
        with pytest.raises(ServiceError) as info:
            await sessions.collect_answers(session)
        return info.value

    failure = asyncio.run(run())
    assert failure.code == LINK and "the evaluator at e:1" in str(failure)


def test_a_garbler_that_lost_a_silent_evaluator_is_reported_after_the_grace(monkeypatch):
    monkeypatch.setattr(sessions, "EVALUATOR_GRACE", 0.01)
    session = _session()
    session.to_g.put(_error(PEER_LOST, "lost the evaluator: link closed"))
    failure = _failure(session)
    assert failure.code == PEER_LOST and "the garbler at g:1" in str(failure)


def test_other_garbler_failures_are_reported_as_they_come(monkeypatch):
    monkeypatch.setattr(sessions, "EVALUATOR_GRACE", 3600.0)  # never waited for
    session = _session()
    session.to_g.put(_error("busy", "at its limit"))
    failure = _failure(session)
    assert failure.code == "busy" and "the garbler at g:1" in str(failure)


def _pool_with(session: SimpleNamespace) -> tuple[AheadPool, list]:
    cancelled: list = []

    async def prepare(circuit_id: str, with_fixed: bool) -> SimpleNamespace:
        raise AssertionError("nothing is prepared here")

    pool = AheadPool(1, prepare, cancelled.append, lambda s, f: False)
    pool._prepared["ops/x"] = deque([session])
    return pool, cancelled


@pytest.mark.parametrize("changed", [True, False])
def test_a_session_whose_tables_changed_while_ahead_goes_to_its_run(changed):
    session = SimpleNamespace(usable=False, refused=False, tables_changed=changed,
                              fixed=None)
    pool, cancelled = _pool_with(session)
    taken = pool.take("ops/x", np.zeros(4, bool))
    if changed:  # the run fails on the evaluator's word (secure.py), naming the link
        assert taken is session and cancelled == []
    else:  # expired or evicted: dropped, and a fresh session serves the run
        assert taken is None and cancelled == [session]
