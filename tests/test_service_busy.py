"""A client retries servers that answer busy (jittered backoff, bounded by busy_wait)
instead of giving up: a fleet larger than the daemons' session limit all finish."""

import asyncio

import numpy as np
import pytest
from daemons import daemons_with

from snail_client.links import ServiceError
from snail_client.secure import AsyncSecureRunner
from snail_common.circuit import evaluate_bits, registry
from snail_common.net.errors import BUSY

CIRCUIT = "ops/fmul-x4"


@pytest.fixture(scope="module")
def services(tmp_path_factory):
    yield from daemons_with(tmp_path_factory, "--max-sessions", "1", "--lane-window-ms", "0")


def _fleet(services, rows, busy_wait):
    async def client(row):
        async with AsyncSecureRunner(services.garbler_addr, services.evaluator_addr,
                                     services.tls_dir, timeout=60, busy_wait=busy_wait) as r:
            return await r.invoke(CIRCUIT, row)

    async def fleet():
        return await asyncio.gather(*(client(row) for row in rows), return_exceptions=True)

    return asyncio.run(fleet())


def test_clients_beyond_the_session_limit_wait_their_turn(services):
    _, schedule = registry.compiled(CIRCUIT)
    rows = np.random.default_rng(4).random((8, schedule.n_inputs)) < 0.5
    runs = _fleet(services, rows, busy_wait=60)
    for inv, want in zip(runs, evaluate_bits(schedule, rows)):
        assert not isinstance(inv, BaseException), inv
        np.testing.assert_array_equal(inv.outputs, want)
    waited = [inv.timing.get("client_busy_wait_s", 0) for inv in runs]
    assert sum(w > 0 for w in waited) >= 1, "no client was ever refused as busy"


def test_busy_past_the_limit_is_an_error_that_says_how_long_it_tried(services):
    _, schedule = registry.compiled(CIRCUIT)
    rows = np.zeros((8, schedule.n_inputs), bool)
    runs = _fleet(services, rows, busy_wait=0)
    errors = [r for r in runs if isinstance(r, BaseException)]
    assert errors, "eight clients at once against one session slot: someone must be refused"
    for exc in errors:
        assert isinstance(exc, ServiceError) and exc.code == BUSY
        assert "--busy-wait limit is 0 s" in str(exc)
