"""The evaluator's timeout names the half that did not come: the garbler's tables, the
client's input labels, or (map-owner setting) the map owner's labels, which it used to
report as the client's."""

from __future__ import annotations

import asyncio
import logging

import pytest

from snail_common.net.chunks import LabelAssembler
from snail_common.net.service import Options
from snail_evaluator.daemon import EvaluatorDaemon
from snail_evaluator.session import Session


class _Client:
    def __init__(self) -> None:
        self.sent: list[dict] = []

    def post(self, msg: dict) -> None:
        self.sent.append(msg)


def _complete(kind: str, n: int) -> LabelAssembler:
    labels = LabelAssembler(kind, n)
    labels.add({"start": 0, "total": n, "labels": bytes(16 * n)})
    return labels


@pytest.mark.parametrize(("garbler", "client_labels", "owner", "named"), [
    (False, _complete("input_labels", 4), None, "the garbler's table stream"),
    (True, LabelAssembler("input_labels", 4), None, "the client's input labels"),
    (True, _complete("input_labels", 4), LabelAssembler("owner_labels", 2),
     "the map owner's labels"),
])
def test_a_session_timeout_names_what_did_not_arrive(garbler, client_labels, owner, named):
    async def expire() -> list[dict]:
        daemon = EvaluatorDaemon(Options(session_timeout=1.0), logging.getLogger("test"))
        client = _Client()
        s = Session(b"\1" * 16, "ops/x", "00", asyncio.get_running_loop().create_future(),
                    client=client, garbler=garbler, labels=client_labels, owner=owner)
        s.ready.add_done_callback(lambda f: f.exception())
        daemon.sessions[s.sid] = s
        daemon.counters["active"] += 1
        daemon._expire(s)
        return client.sent

    (error,) = asyncio.run(expire())
    assert error["code"] == "timeout"
    assert error["message"].startswith(f"{named} did not arrive within 1 s")
