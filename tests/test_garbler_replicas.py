"""The garbler streams to the evaluator replica its client talks to, and dials only the
evaluators its operator named (``--evaluator``, repeatable, each a name that may resolve
to several replicas): a request naming another address is refused as ``forbidden`` and
that address is never dialled; one naming an allowed replica that is gone (another
instance answers there) is ``peer_lost``, which a client retries elsewhere."""

from __future__ import annotations

import asyncio
import json
import secrets

import numpy as np
import pytest
from test_garbler_map_owners import Listener, garbler

from snail_client.blocking import SecureRunner
from snail_client.embedded import start_daemon
from snail_common.circuit import evaluate_bits, registry
from snail_common.gc import fresh_delta, labels_to_bytes
from snail_common.net import errors, messages, replicas, tls
from snail_common.net.conn import connect, parse_addr
from snail_common.net.errors import ProtocolError
from snail_common.net.tls import make_certs

CIRCUIT = "ops/fmul-x4"


@pytest.fixture(scope="module")
def tls_dir(tmp_path_factory):
    return make_certs(tmp_path_factory.mktemp("tls"))


@pytest.fixture(scope="module")
def evaluators(tmp_path_factory, tls_dir):
    """Two evaluator replicas (one operator, two addresses)."""
    root = tmp_path_factory.mktemp("evaluators")
    daemons = [start_daemon("evaluator", ["--tls-dir", str(tls_dir), "--log-level", "info"],
                            root / f"evaluator{i}.log") for i in range(2)]
    yield daemons
    for daemon in daemons:
        daemon.stop()


@pytest.fixture()
def listener():
    target = Listener()
    yield target
    target.close()


def raw_request(garbler_addr: str, tls_dir, **named: str) -> dict:
    """A client's garble_request naming an evaluator replica (``named``); the garbler's
    answer for it."""
    iface = registry.interface(CIRCUIT)

    async def ask() -> dict:
        ctx = tls.client_context(tls_dir, "client")
        conn = await connect(*parse_addr(garbler_addr), ctx, "client", "garbler")
        sid = secrets.token_bytes(16)
        conn.write(messages.make("garble_request", sid=sid, circuit=CIRCUIT,
                                 hash=iface.content_hash, seed=secrets.token_bytes(16),
                                 delta=labels_to_bytes(fresh_delta()),
                                 key=secrets.token_bytes(16), **named))
        try:
            while True:
                msg, _ = await conn.recv(60)
                if msg.get("sid") == sid and msg["t"] == "error":
                    return msg
        finally:
            await conn.close()

    return asyncio.run(ask())


@pytest.mark.parametrize("instance", [None, "0123456789abcdef"],
                         ids=["address_only", "with_an_unknown_instance"])
def test_an_evaluator_outside_the_operators_names_is_refused_and_never_dialled(
        tmp_path, tls_dir, evaluators, listener, instance):
    extra = {"evaluator_id": instance} if instance else {}
    with garbler(tmp_path, tls_dir, evaluators[0]) as daemon:
        reply = raw_request(daemon.address, tls_dir,
                            evaluator=f"127.0.0.1:{listener.port}", **extra)
        assert reply["code"] == errors.FORBIDDEN, reply
        assert "field 'evaluator'" in reply["message"]
        assert f"127.0.0.1:{listener.port} is not an evaluator this server may dial" \
            in reply["message"]
        assert f"--evaluator {evaluators[0].address}" in reply["message"]
        assert listener.dialled() == 0


def test_an_allowed_address_answered_by_another_instance_is_a_lost_replica(
        tmp_path, tls_dir, evaluators):
    """The address is one the operator allowed, but the replica there is not the one the
    client talks to (it restarted, or the address was reused): retryable, not served."""
    with garbler(tmp_path, tls_dir, evaluators[0]) as daemon:
        reply = raw_request(daemon.address, tls_dir, evaluator=evaluators[0].address,
                            evaluator_id="0123456789abcdef")
        assert reply["code"] == errors.PEER_LOST, reply
        assert "is gone" in reply["message"]


def _sessions(log) -> int:
    return sum(json.loads(line).get("event") == "session"
               for line in log.read_text().splitlines())


def test_each_session_streams_to_the_replica_its_client_talks_to(tmp_path, tls_dir,
                                                                evaluators):
    """One garbler, two evaluator replicas: a client of either gets correct results, and
    the tables went to the replica it talks to (the session log lines say where)."""
    _, schedule = registry.compiled(CIRCUIT)
    rows = np.random.default_rng(7).random((2, schedule.n_inputs)) < 0.5
    flags = [f for e in evaluators for f in ("--evaluator", e.address)]
    with garbler(tmp_path, tls_dir, evaluators[0], *flags[2:]) as daemon:
        for evaluator, row in zip(evaluators, rows):
            before = [_sessions(e.log) for e in evaluators]
            with SecureRunner(daemon.address, evaluator.address, tls_dir, timeout=60) as r:
                out = r.run(CIRCUIT, row)
            np.testing.assert_array_equal(out, evaluate_bits(schedule, row[None])[0])
            after = [_sessions(e.log) for e in evaluators]
            assert [a - b for a, b in zip(after, before)] == [
                int(e is evaluator) for e in evaluators]


def test_a_replica_that_left_dns_stays_dialable_while_it_drains(monkeypatch):
    """A swarm drops a stopping task from tasks.NAME at once, while it drains: the
    garbler must still reach it for the sessions it admitted (once rejected as
    forbidden, failing a localization under a rolling update). An address the names
    never resolved to stays forbidden, and one gone for longer than RECENT_S too."""
    answers = [[("10.0.0.1", 7000), ("10.0.0.2", 7000)], [("10.0.0.2", 7000)]]

    async def fake(host, port):
        return list(answers[0])

    monkeypatch.setattr(replicas, "resolve", fake)
    names = replicas.Replicas([("tasks.evaluator", 7000)], "--evaluator", "evaluator", ttl=0)

    async def check() -> None:
        assert await names.allowed(("10.0.0.1", 7000)) == ("10.0.0.1", 7000)
        answers.pop(0)  # 10.0.0.1 is draining: out of DNS
        assert await names.addresses(fresh=True) == [("10.0.0.2", 7000)]
        assert await names.allowed(("10.0.0.1", 7000)) == ("10.0.0.1", 7000)
        assert await names.allowed(("10.0.0.3", 7000)) is None
        with pytest.raises(ProtocolError) as refused:
            await names.check("10.0.0.3:7000", "evaluator")
        assert refused.value.code == errors.FORBIDDEN
        names._seen[("10.0.0.1", 7000)] -= replicas.RECENT_S  # long gone
        assert await names.allowed(("10.0.0.1", 7000)) is None

    asyncio.run(check())
