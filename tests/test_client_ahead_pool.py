"""The client's garble-ahead pool on its own (fake servers): how many sessions it keeps
prepared, with which frame's labels, and what it does with them when the frame changes."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace

import numpy as np

from snail_client.ahead import AheadPool
from snail_client.sessions import FixedInputs

CIRCUIT = "ops/x"
OTHER = "ops/y"
MASK = np.array([False, False, True, True])


def _frame(a: bool, b: bool) -> FixedInputs:
    return FixedInputs(MASK, np.array([False, False, a, b]))


class _Servers:
    """Prepares fake sessions and records what the pool asks."""

    def __init__(self) -> None:
        self.prepared: list[SimpleNamespace] = []
        self.cancelled: list[SimpleNamespace] = []
        self.adopted: list[SimpleNamespace] = []
        self.pool = AheadPool(3, self.prepare, self.cancelled.append, self.adopt)

    async def prepare(self, circuit_id: str, with_fixed: bool) -> SimpleNamespace:
        fixed = self.pool.fixed(circuit_id) if with_fixed else None
        session = SimpleNamespace(usable=True, refused=False, tables_changed=False,
                                  owner_bits=0, frame=None,
                                  fixed=fixed)
        self.prepared.append(session)
        return session

    def adopt(self, session: SimpleNamespace, fixed: FixedInputs) -> bool:
        self.adopted.append(session)
        session.fixed = fixed
        return True

    async def frame(self, fixed: FixedInputs, invocations: int,
                    circuit: str = CIRCUIT) -> list[SimpleNamespace]:
        """A frame as a localization makes it: expect, then its invocations in turn."""
        self.pool.expect(circuit, invocations, fixed)
        used = []
        for _ in range(invocations):
            await asyncio.sleep(0)
            bits = fixed.bits | np.array([True, False, False, False])  # a pose bit
            session = (self.pool.take(circuit, bits)
                       or await self.pool.in_flight(circuit, bits))
            assert session is not None and FixedInputs.same(session.fixed, fixed)
            used.append(session)
            self.pool.used(circuit)
            self.pool.fill(circuit)
        await self.settle()
        return used

    async def settle(self) -> None:
        """Let every preparation under way finish (and its callback run)."""
        await asyncio.gather(*self.pool._filling)
        await asyncio.sleep(0)

    def queued(self, circuit: str = CIRCUIT) -> list[SimpleNamespace]:
        return list(self.pool._prepared.get(circuit, ()))


def test_a_single_frame_prepares_only_its_own_invocations():
    async def scenario():
        servers = _Servers()
        await servers.frame(_frame(True, False), 5)
        return servers

    servers = asyncio.run(scenario())
    assert len(servers.prepared) == 5 and not servers.queued() and not servers.cancelled


def test_a_sequence_keeps_its_depth_garbled_between_frames():
    """From a circuit's second frame on, the sessions beyond the frame's invocations are
    garbled without its labels, and the next frame sends its own for them: none is
    cancelled and the next frame's first invocation does not wait for a garbling."""
    async def scenario():
        servers = _Servers()
        await servers.frame(_frame(True, False), 5)
        await servers.frame(_frame(False, True), 5)
        warm = servers.queued()
        assert len(warm) == 3 and all(s.fixed is None for s in warm)
        prepared = len(servers.prepared)
        used = await servers.frame(_frame(True, True), 5)
        return servers, warm, used, prepared

    servers, warm, used, prepared = asyncio.run(scenario())
    assert used[:3] == warm and servers.adopted == warm
    assert not servers.cancelled
    assert len(servers.prepared) == prepared + 2 + 3  # the frame's other 2, then 3 warm


def test_a_frame_of_another_circuit_cancels_the_sessions_kept_warm():
    """A sequence whose frames change circuit (another number of points) must not leave
    each circuit's warm sessions at the servers: the garbler's sessions and the
    evaluator's table buffer would fill with sessions no frame uses."""
    async def scenario():
        servers = _Servers()
        for _ in range(2):
            await servers.frame(_frame(True, False), 5)
        warm = servers.queued()
        await servers.frame(_frame(False, True), 5, circuit=OTHER)
        await servers.frame(_frame(True, True), 5, circuit=OTHER)
        return servers, warm

    servers, warm = asyncio.run(scenario())
    assert len(warm) == 3 and all(s in servers.cancelled for s in warm)
    assert not servers.queued() and len(servers.queued(OTHER)) == 3


def test_a_reservation_the_servers_refused_shrinks_the_pool_until_it_has_been_quiet():
    """A server with no room for a reservation (busy) or that gave one's place to a live
    session (evicted): the pool holds one fewer at once, and grows back by one only after
    REGROW_AFTER invocations without another refusal."""
    from snail_client.ahead import REGROW_AFTER

    async def scenario():
        servers = _Servers()
        fixed = _frame(True, False)
        servers.pool.expect(CIRCUIT, 100, fixed)
        await servers.settle()
        assert len(servers.queued()) == 3
        for session in servers.queued()[:2]:  # two answered busy / evicted
            session.usable, session.refused = False, True
        bits = fixed.bits | np.array([True, False, False, False])
        depths = []
        for _ in range(2 * REGROW_AFTER + 2):
            session = (servers.pool.take(CIRCUIT, bits)
                       or await servers.pool.in_flight(CIRCUIT, bits))
            assert session is not None and not session.refused
            servers.pool.used(CIRCUIT)
            servers.pool.fill(CIRCUIT)
            await servers.settle()
            depths.append((servers.pool.depth, len(servers.queued())))
        return depths

    depths = asyncio.run(scenario())
    assert depths[0] == (1, 1)  # 3 -> 2 -> 1: one fewer per refusal
    assert all(d == (1, 1) for d in depths[:REGROW_AFTER - 2])
    assert depths[REGROW_AFTER] == (2, 2)  # quiet for REGROW_AFTER: one more
    assert depths[-1] == (3, 3)


def test_frames_of_one_run_keep_the_sessions_they_do_not_need_warm():
    """A tracked stream makes one run a frame: its frame adopts one warm session, the
    others stay warm for the next frames (they were each adopted and then cancelled by
    the next frame: a garbled session thrown away every other frame, 40-48 frames/s
    instead of 92-94)."""
    async def scenario():
        servers = _Servers()
        await servers.frame(_frame(True, False), 5)
        for k in range(6):
            await servers.frame(_frame(bool(k % 2), True), 1)
        return servers

    servers = asyncio.run(scenario())
    assert not servers.cancelled  # before: 4 cancelled, 11 adopted, 18 prepared
    assert len(servers.adopted) == 5  # one a frame from the third (the second's was new)
    assert len(servers.prepared) == 5 + 3 + 6  # the first frame, 3 warm, 1 more a frame
