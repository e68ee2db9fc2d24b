"""The pacer of ``--rate`` (snail_client/threaded.py) on a stand-in runner: a stream that
ends while a padding frame is part way lets that frame finish its runs on its own ticks
(a run cut off would be a failed session in the servers' logs), and counts every run it
made, so the servers' count of runs is the tracker's; where runs take longer than a
tick, padding frames never pile up beyond the frames in flight (a loaded machine's runs
did, until the servers refused them as busy)."""

from __future__ import annotations

import asyncio

import pytest

from snail_client.threaded import Pacer

CIRCUIT = "ops/fadd-x1"


class CountingRunner:
    """What the pacer calls on a secure runner, counting the runs."""

    def __init__(self) -> None:
        self.runs = 0

    def fixed(self, circuit_id: str) -> None:
        return None

    def expect(self, circuit_id: str, runs: int, fixed: object) -> None:
        pass

    async def invoke(self, circuit_id: str, bits: object) -> None:
        self.runs += 1


def test_a_pacer_closed_mid_padding_frame_finishes_that_frame_and_counts_it():
    async def scenario():
        runner = CountingRunner()
        pacer = Pacer(runner, rate=200.0, runs=3)
        pacer.circuit = CIRCUIT  # a frame ran: padding may follow
        pacer.start()
        while runner.runs % 3 != 1:  # a padding frame part way: one run of three made
            await asyncio.sleep(0.001)
        # the old close stopped the ticks first: the frame's next run waited 30 s for one
        await asyncio.wait_for(pacer.close(), 10)  # a hang guard (ticks are 5 ms)
        return pacer, runner

    pacer, runner = asyncio.run(scenario())
    assert pacer.padding_frames >= 1
    assert pacer.padding_runs == runner.runs == 3 * pacer.padding_frames


class SlowRunner(CountingRunner):
    """Runs that take many ticks, counting how many are under way at once."""

    def __init__(self) -> None:
        super().__init__()
        self.running = self.most = 0

    async def invoke(self, circuit_id: str, bits: object) -> None:
        self.running += 1
        self.most = max(self.most, self.running)
        await asyncio.sleep(0.05)  # 50 ticks of 1 ms
        self.running -= 1
        self.runs += 1


@pytest.mark.parametrize("depth", [1, 2])
def test_padding_runs_longer_than_a_tick_never_pile_up(depth):
    async def scenario():
        runner = SlowRunner()
        pacer = Pacer(runner, rate=1000.0, runs=1, depth=depth)
        pacer.circuit = CIRCUIT
        pacer.start()
        while runner.runs < 6:
            await asyncio.sleep(0.005)
        await asyncio.wait_for(pacer.close(), 30)  # a hang guard
        return pacer, runner

    pacer, runner = asyncio.run(scenario())
    assert 1 <= runner.most <= depth
    assert pacer.padding_runs == runner.runs and pacer.padding_failed == 0
