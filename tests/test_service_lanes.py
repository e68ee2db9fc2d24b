"""Lanes in the daemons: concurrent sessions of one circuit garbled and evaluated in one
pass, each client still getting exactly its own result."""

import asyncio

import numpy as np
import pytest

from snail_client.embedded import embedded_services
from snail_client.secure import AsyncSecureRunner
from snail_common.circuit import evaluate_bits, registry

CIRCUIT = "ops/fmul-x4"


@pytest.fixture(scope="module")
def services(tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache")
    with embedded_services(env={"SNAIL_CACHE_DIR": str(cache)},
                           extra_args=("--lane-window-ms", "300", "--max-lanes", "8")) as svc:
        yield svc


def test_concurrent_clients_share_a_pass_and_get_their_own_results(services):
    _, schedule = registry.compiled(CIRCUIT)
    rng = np.random.default_rng(11)
    bits = rng.random((5, schedule.n_inputs)) < 0.5

    async def client(row):
        async with AsyncSecureRunner(services.garbler_addr, services.evaluator_addr,
                                     services.tls_dir, timeout=60) as r:
            return await r.invoke(CIRCUIT, row)

    async def fleet():
        return await asyncio.gather(*(client(row) for row in bits))

    runs = asyncio.run(fleet())
    want = evaluate_bits(schedule, bits)
    for inv, expected in zip(runs, want):
        np.testing.assert_array_equal(inv.outputs, expected)
    for role in ("garbler", "evaluator"):
        lanes = [inv.timing[f"{role}_lanes"] for inv in runs]
        assert max(lanes) > 1, f"the {role} formed no batch: lanes per run {lanes}"


def test_a_lone_request_runs_alone_after_the_window(services):
    _, schedule = registry.compiled(CIRCUIT)
    row = np.ones(schedule.n_inputs, bool)

    async def one():
        async with AsyncSecureRunner(services.garbler_addr, services.evaluator_addr,
                                     services.tls_dir, timeout=60) as r:
            return await r.invoke(CIRCUIT, row)

    inv = asyncio.run(one())
    np.testing.assert_array_equal(inv.outputs, evaluate_bits(schedule, row[None])[0])
    assert inv.timing["garbler_lanes"] == inv.timing["evaluator_lanes"] == 1
