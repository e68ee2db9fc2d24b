"""Found by ``snail-bench soak`` (16 clients): under load one invocation takes longer
than ``--session-timeout``, so the session a client had garbled ahead expired while the
client was still busy with the one before it. The evaluator failed it (the client then
garbled it again, or lost the run when it had just sent the labels) and the garbler gave
up waiting for its ``done``. A garbled-ahead session is queued, not idle, while its
client has an earlier session under way: it must wait (up to ``--idle-timeout``)."""

from __future__ import annotations

import time

import numpy as np

from snail_client.blocking import SecureRunner
from snail_client.embedded import start_daemon
from snail_common.circuit import evaluate_bits, registry
from snail_common.net.tls import make_certs
from tests.daemons import session_outcomes, start_patched_evaluator

# the evaluator, with each first session of a connection held for 3 s after its
# evaluation (a loaded machine, deterministically): the session the client garbled
# ahead meanwhile waits for its labels three times the session timeout
SLOW_FIRST_SESSION = """
import asyncio
from snail_evaluator import daemon
from snail_evaluator.cli import main

original = daemon.EvaluatorDaemon._evaluate
held = set()

async def evaluate_slowly_the_first_time(self, conn, s, schedule):
    result = await original(self, conn, s, schedule)
    if s.client not in held:
        held.add(s.client)
        await asyncio.sleep(3.0)
    return result

daemon.EvaluatorDaemon._evaluate = evaluate_slowly_the_first_time
main(prog_name="snail-evaluator")
"""
CIRCUIT = "ops/fmul-x4"
TIMEOUT = ["--session-timeout", "1"]


def test_a_session_garbled_ahead_waits_while_its_client_is_busy(tmp_path):
    tls_dir = make_certs(tmp_path / "tls")
    evaluator = start_patched_evaluator(SLOW_FIRST_SESSION, tmp_path / "evaluator.log",
                                        "--tls-dir", str(tls_dir), *TIMEOUT)
    garbler = None
    try:
        garbler = start_daemon("garbler", ["--evaluator", evaluator.address, "--tls-dir",
                                           str(tls_dir), "--log-level", "info", *TIMEOUT],
                               tmp_path / "garbler.log")
        _, schedule = registry.compiled(CIRCUIT)
        rng = np.random.default_rng(7)
        with SecureRunner(garbler.address, evaluator.address, tls_dir, timeout=30,
                          ahead=1) as runner:
            runner.expect(CIRCUIT, 2)
            ahead = []
            for _ in range(2):
                bits = rng.random(schedule.n_inputs) < 0.5
                outputs = runner.run(CIRCUIT, bits)
                np.testing.assert_array_equal(outputs, evaluate_bits(schedule, bits[None])[0])
                ahead.append(runner.last.garbled_ahead)
        time.sleep(0.5)  # the daemons' session lines
        assert session_outcomes(evaluator.log) == ["ok", "ok"]
        assert session_outcomes(garbler.log) == ["ok", "ok"]
        assert ahead[1] > 0  # the second session's tables were all in before its labels
    finally:
        if garbler is not None:
            garbler.stop()
        evaluator.stop()
