"""Lanes in the daemons: concurrent sessions of one circuit garbled and evaluated in one
pass, each client still getting exactly its own result."""

import asyncio

import numpy as np
import pytest
from daemons import daemons_with

from snail_client.secure import AsyncSecureRunner
from snail_common.circuit import evaluate_bits, registry

CIRCUIT = "ops/fmul-x4"


@pytest.fixture(scope="module")
def services(tmp_path_factory):
    yield from daemons_with(tmp_path_factory, "--lane-window-ms", "300", "--max-lanes", "8")


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


def test_a_lone_run_never_waits_for_the_window_and_a_fleet_does():
    """No other run of the circuit under way: no batch (a window of 1000 s would show);
    with one under way, the next ones wait for the window and share a pass."""
    from snail_evaluator.lanes import EvalLane, LaneBatcher, Solo

    _, schedule = registry.compiled(CIRCUIT)
    labels = np.zeros((schedule.n_inputs + 2, 2), np.uint64)

    async def scenario():
        batcher = LaneBatcher(window_s=1000, max_lanes=2)
        first = await asyncio.wait_for(batcher.lane(CIRCUIT, schedule, labels), 1.0)
        assert isinstance(first, Solo)
        # the first still runs: two more form a batch, closed at once by max_lanes
        second, third = await asyncio.wait_for(asyncio.gather(
            batcher.lane(CIRCUIT, schedule, labels),
            batcher.lane(CIRCUIT, schedule, labels)), 1.0)
        assert isinstance(second, EvalLane) and isinstance(third, EvalLane)
        assert second.lanes == third.lanes == 2
        for _ in range(3):
            batcher.release(CIRCUIT)
        alone = await asyncio.wait_for(batcher.lane(CIRCUIT, schedule, labels), 1.0)
        assert isinstance(alone, Solo)

    asyncio.run(scenario())


def test_a_clients_own_garbled_ahead_request_never_waits_and_anothers_does():
    """A lone client garbles ahead: its next request arrives while its own run is under
    way and must not wait out the window (1000 s would show); another client's request
    still waits and, with a third, shares a pass."""
    from snail_garbler.lanes import LaneBatcher, LaneView

    _, schedule = registry.compiled(CIRCUIT)
    secret = (bytes(16), bytes(16), bytes(16))
    me, you, them = object(), object(), object()

    async def scenario():
        batcher = LaneBatcher(window_s=1000, max_lanes=2)

        def lane(client):
            return batcher.lane(CIRCUIT, schedule, *secret, 64, 4096, client)

        assert await asyncio.wait_for(lane(me), 1.0) is None
        assert await asyncio.wait_for(lane(me), 1.0) is None  # ahead: its own run only
        yours, theirs = await asyncio.wait_for(asyncio.gather(lane(you), lane(them)), 1.0)
        assert isinstance(yours, LaneView) and isinstance(theirs, LaneView)
        assert yours.lanes == theirs.lanes == 2
        for client in (me, me, you, them):
            batcher.release(CIRCUIT, client)
        assert await asyncio.wait_for(lane(you), 1.0) is None  # nothing under way
        batcher.release(CIRCUIT, you)

    asyncio.run(scenario())
