"""Found by ``snail-bench soak`` (16 clients, 10 minutes): under load the garbler stops
waiting for the evaluator's ``done`` (its session timeout) and drops the connection while
the evaluator is still evaluating. The evaluator then failed to write ``done`` and left
the session unended: the client got neither its result nor an error until its own
300 s timeout, and the session held its slot meanwhile. The result is the client's
either way; it must get it, and the session must end."""

from __future__ import annotations

import numpy as np

from snail_client.blocking import SecureRunner
from snail_client.embedded import start_daemon
from snail_common.circuit import evaluate_bits, registry
from snail_common.net.tls import make_certs
from tests.daemons import session_outcomes, start_patched_evaluator

# the evaluator, with the garbler's connection lost once each session's evaluation is done
# and the garbler has answered the client (deterministically, where under load the
# garbler's timeout makes it happen by a race)
LOSES_THE_GARBLER = """
import asyncio
from snail_evaluator import daemon
from snail_evaluator.cli import main

original = daemon.EvaluatorDaemon._evaluate

async def evaluate_then_lose_the_garbler(self, conn, s, schedule):
    result = await original(self, conn, s, schedule)
    await asyncio.sleep(0.5)
    conn.abort()
    return result

daemon.EvaluatorDaemon._evaluate = evaluate_then_lose_the_garbler
main(prog_name="snail-evaluator")
"""
CIRCUIT = "ops/fmul-x4"


def test_the_client_gets_its_result_when_the_garbler_stops_waiting(tmp_path):
    tls_dir = make_certs(tmp_path / "tls")
    evaluator = start_patched_evaluator(LOSES_THE_GARBLER, tmp_path / "evaluator.log",
                                        "--tls-dir", str(tls_dir))
    garbler = None
    try:
        garbler = start_daemon("garbler", ["--evaluator", evaluator.address, "--tls-dir",
                                           str(tls_dir), "--log-level", "info"],
                               tmp_path / "garbler.log")
        _, schedule = registry.compiled(CIRCUIT)
        rng = np.random.default_rng(5)
        with SecureRunner(garbler.address, evaluator.address, tls_dir, timeout=20) as runner:
            for _ in range(2):  # the second run needs a fresh garbler-evaluator connection
                bits = rng.random(schedule.n_inputs) < 0.5
                outputs = runner.run(CIRCUIT, bits)  # not the client's timeout's error
                np.testing.assert_array_equal(outputs, evaluate_bits(schedule, bits[None])[0])
            health = runner.health("evaluator")["sessions"]
        assert health["active"] == 0 and health["done"] == 2
        assert session_outcomes(evaluator.log) == ["ok", "ok"]
    finally:
        if garbler is not None:
            garbler.stop()
        evaluator.stop()
