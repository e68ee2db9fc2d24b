"""SIGTERM drains a daemon (what an orchestrator's rolling update or scale-down sends): it
refuses new sessions with the retryable ``draining``, finishes the sessions under way
within ``--grace`` and exits 0. Real daemons, real signals."""

from __future__ import annotations

import asyncio
import json
import signal

import numpy as np
import pytest

from snail_client.embedded import embedded_services
from snail_client.links import ServiceError
from snail_client.secure import AsyncSecureRunner
from snail_client.sessions import collect_answers
from snail_common.circuit import evaluate_bits, registry
from snail_common.net.errors import DRAINING

CIRCUIT = "ops/fmul-x4"


def _events(log) -> list[dict]:
    return [json.loads(line) for line in log.read_text().splitlines() if line.startswith("{")]


@pytest.mark.parametrize("role", ["garbler", "evaluator"])
def test_sigterm_finishes_the_session_under_way_refuses_new_ones_and_exits_0(role):
    _, schedule = registry.compiled(CIRCUIT)  # compiled here: the daemons load it
    rows = np.random.default_rng(11).random((2, schedule.n_inputs)) < 0.5
    with embedded_services(log_level="info", extra_args=("--grace", "30")) as svc:
        daemon = svc.garbler if role == "garbler" else svc.evaluator

        async def drained():
            async with AsyncSecureRunner(svc.garbler_addr, svc.evaluator_addr, svc.tls_dir,
                                         timeout=60, busy_wait=0) as r:
                r.expect(CIRCUIT, 1)  # one session garbled ahead: under way on both
                while not r.ahead._prepared.get(CIRCUIT):
                    await asyncio.sleep(0.05)
                daemon.process.send_signal(signal.SIGTERM)
                await asyncio.sleep(1.0)  # the daemon is draining, the session still open
                assert daemon.process.poll() is None, "exited with a session under way"
                late = await r._prepare(CIRCUIT, fixed=False)  # a new session: refused
                with pytest.raises(ServiceError) as refused:
                    await collect_answers(late)
                first = await r.invoke(CIRCUIT, rows[0])  # the session under way
                return first.outputs, refused.value

        outputs, refused = asyncio.run(drained())
        np.testing.assert_array_equal(outputs, evaluate_bits(schedule, rows[:1])[0])
        assert refused.code == DRAINING, refused
        assert daemon.process.wait(60) == 0
        events = _events(daemon.log)
        kinds = [e["event"] for e in events]
        assert "shutting_down" in kinds and kinds[-1] == "stopped"
        # it left once its sessions were done, not when the 30 s grace ran out
        assert events[-1]["sessions_cut"] == 0
        outcomes = [e["outcome"] for e in events if e["event"] == "session"]
        assert "ok" in outcomes and DRAINING in outcomes, outcomes
