"""A client spreads its sessions over the replicas a name resolves to and, when one is lost
mid-run, runs the invocation again on another: the pose is the cleartext one, the result
counts the retry, and no invocation is lost or counted twice.

One garbler (allowed both evaluators) and two evaluator replicas on loopback; the
client's name for the evaluators resolves to both (the resolver is replaced in this
process: an orchestrator's DNS would do the same for tasks.evaluator)."""

from __future__ import annotations

import json
import signal
import time

import numpy as np
import pytest
from shared_paths import EXAMPLES

from snail_client import replicas
from snail_client.blocking import SecureRunner
from snail_client.embedded import start_daemon
from snail_client.localize import GarbledBackend, Options, localize
from snail_common.circuit import evaluate_bits, registry
from snail_common.loc.backends import CircuitBackend
from snail_common.loc.problem import load_problem
from snail_common.net.conn import parse_addr
from snail_common.net.tls import make_certs

NAME = "evaluators.snail.test"  # the name the client is given; its certificate says it
CIRCUIT = "ops/fmul-x4"


@pytest.fixture(scope="module")
def servers(tmp_path_factory):
    root = tmp_path_factory.mktemp("replicas")
    tls_dir = make_certs(root / "tls", hosts=[NAME])
    common = ["--tls-dir", str(tls_dir), "--log-level", "info"]
    evaluators = [start_daemon("evaluator", common, root / f"evaluator{i}.log")
                  for i in range(2)]
    flags = [f for e in evaluators for f in ("--evaluator", e.address)]
    garbler = start_daemon("garbler", [*flags, *common], root / "garbler.log")
    yield tls_dir, garbler, evaluators
    for daemon in (garbler, *evaluators):
        daemon.stop()


def _ok_sessions(daemon) -> int:
    return sum(e.get("event") == "session" and e.get("outcome") == "ok"
               for e in map(json.loads, daemon.log.read_text().splitlines()))


def _settled_ok_sessions(daemon) -> int:
    """The ok sessions once the daemon has logged its last ones (a client may hold its
    result a moment before the daemon writes the session's line)."""
    count, deadline = _ok_sessions(daemon), time.monotonic() + 10
    while time.monotonic() < deadline:
        time.sleep(0.5)
        count, last = _ok_sessions(daemon), count
        if count == last:
            break
    return count


def test_sessions_are_spread_over_every_replica(servers, monkeypatch):
    tls_dir, garbler, evaluators = servers
    live = [e for e in evaluators if e.process.poll() is None]
    if len(live) < 2:
        pytest.skip("an evaluator was killed by the failover test, which runs after this")
    addresses = [parse_addr(e.address) for e in live]

    async def both(host, port):
        return list(addresses) if host == NAME else [(host, port)]

    monkeypatch.setattr(replicas, "resolve", both)
    before = [_settled_ok_sessions(e) for e in live]
    with SecureRunner(garbler.address, f"{NAME}:{addresses[0][1]}", tls_dir,
                      timeout=60) as runner:
        problem = load_problem(EXAMPLES / "synthetic_n6.json")
        localize(problem, Options(backend="garbled", min_invocations=10),
                 GarbledBackend(runner))
    served = [_settled_ok_sessions(e) - b for e, b in zip(live, before)]
    assert all(n >= 3 for n in served), served


def test_a_replica_lost_mid_run_is_retried_on_another_with_the_same_pose(servers,
                                                                          monkeypatch):
    tls_dir, garbler, evaluators = servers
    addresses = [parse_addr(e.address) for e in evaluators]

    async def both(host, port):
        return list(addresses) if host == NAME else [(host, port)]

    monkeypatch.setattr(replicas, "resolve", both)
    problem = load_problem(EXAMPLES / "synthetic_n6.json")
    clear = localize(problem, Options(backend="cleartext"), CircuitBackend())
    options = Options(backend="garbled", min_invocations=20)
    with SecureRunner(garbler.address, f"{NAME}:{parse_addr(evaluators[0].address)[1]}",
                      tls_dir, timeout=60, busy_wait=60) as runner:
        pool, taken, killed = runner._runner.ahead, [0], []
        take = pool.take

        def take_then_lose_its_evaluator(*args):
            """The fifth session the client takes loses its evaluator replica just before
            its inputs go out (SIGKILL: no goodbye)."""
            session = take(*args)
            taken[0] += 1
            if session is not None and taken[0] == 5:
                port = session.evaluator.conn.peer[1]
                (victim,) = [e for e in evaluators if parse_addr(e.address)[1] == port]
                victim.process.send_signal(signal.SIGKILL)
                victim.process.wait(10)
                killed.append(victim)
            return session

        monkeypatch.setattr(pool, "take", take_then_lose_its_evaluator)
        result = localize(problem, options, GarbledBackend(runner))
        assert killed, "no session was taken from the pool after four"
        survivor = next(e for e in evaluators if e is not killed[0])
        before = _settled_ok_sessions(survivor)
        again = localize(problem, options, GarbledBackend(runner))  # on the survivor
        assert _settled_ok_sessions(survivor) - before == again["invocations"]
        assert runner.invocations == result["invocations"] + again["invocations"]
    for key in ("rvec", "tvec", "iterations", "status", "cost"):
        assert result[key] == clear[key] == again[key], key
    assert result["retries"] >= 1 and again["retries"] == 0
    assert result["invocations"] == 20  # padded as asked: no invocation lost or doubled
    assert _ok_sessions(killed[0]) >= 1  # both replicas had served sessions


def test_an_evaluator_replica_the_garbler_does_not_know_is_passed_over(tmp_path,
                                                                        monkeypatch):
    """In a rolling update a garbler replica started after an evaluator replica left DNS
    (draining) refuses it as ``forbidden`` (it cannot tell it from an address it must not
    dial); a client that knows other evaluator replicas runs the invocation on one of them
    (deploy/swarm-test lost a localization to it from a fresh clone). Here the garbler is
    allowed evaluator 0 only, and the client's name resolves to both; nothing is garbled
    ahead, so every session is asked for by an invocation."""
    tls_dir = make_certs(tmp_path / "tls", hosts=[NAME])
    common = ["--tls-dir", str(tls_dir), "--log-level", "info"]
    evaluators = [start_daemon("evaluator", common, tmp_path / f"evaluator{i}.log")
                  for i in range(2)]
    garbler = start_daemon("garbler", ["--evaluator", evaluators[0].address, *common],
                           tmp_path / "garbler.log")
    try:
        addresses = [parse_addr(e.address) for e in evaluators]

        async def both(host, port):
            return list(addresses) if host == NAME else [(host, port)]

        monkeypatch.setattr(replicas, "resolve", both)
        _, schedule = registry.compiled(CIRCUIT)
        rng = np.random.default_rng(3)
        with SecureRunner(garbler.address, f"{NAME}:{addresses[1][1]}", tls_dir,
                          timeout=60, busy_wait=60) as runner:
            for _ in range(6):  # the replicas taken in turn: evaluator 1 at least thrice
                bits = rng.random(schedule.n_inputs) < 0.5
                np.testing.assert_array_equal(runner.run(CIRCUIT, bits),
                                              evaluate_bits(schedule, bits[None])[0])
            assert runner.invocations == 6 and runner._runner.retries >= 1
        assert _settled_ok_sessions(evaluators[0]) == 6
        assert _ok_sessions(evaluators[1]) == 0
    finally:
        for daemon in (garbler, *evaluators):
            daemon.stop()
