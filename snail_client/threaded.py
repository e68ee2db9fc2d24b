"""The secure runner shared by threads: frames in flight, and runs at a constant rate.

``SecureRunner`` is blocking and single-threaded: each call runs its event loop until the
call is done. A tracker with frames in flight (``--in-flight D``) solves D frames at once,
each in a worker thread, and their runs must go concurrently over the same two
connections (the runner multiplexes sessions by id). ``ThreadedRunner`` runs the loop in a
thread of its own for the length of a stream and gives each worker the blocking calls a
garbled backend makes (``invoke``, ``expect``, ``fixed``, ``use_frame``), each a coroutine
submitted to that loop.

``--rate R`` (``Pacer``): secure runs at R per second whatever the frames. Time is cut in
ticks of 1/R s, and a *slot* is the ticks one frame's runs take (K, or a padded frame's
until it is done). At each slot's start the oldest frame waiting for one takes it; when
none waits, a padding frame does: the last frame's inputs declared again (their labels go
to the evaluator, as a real frame's do) and K runs on random bits, which the servers
cannot tell from a frame's. One run may start per tick; a run that is not ready when its
tick comes starts when it is, and the ticks never bunch. A padding slot opens only while
fewer frames than the tracker's frames in flight are under way (``depth``), real frames
and padding frames alike: where runs take longer than a tick, padding keeps the pace the
frames would have, rather than piling runs up until the servers refuse them. From the
first frame to the last the servers see the same circuit at the same pace: frame timing
and dropped frames are hidden too. Before the first frame nothing runs (no circuit is known yet).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import os
import threading
from collections import deque
from collections.abc import Coroutine
from typing import Any

import numpy as np

from snail_common.circuit import registry

from .audit import Audits
from .blocking import SecureRunner
from .secure import AsyncSecureRunner
from .sessions import FixedInputs, Invocation

SEEN_RUNS = 64


class Gate:
    """One slot of the pacer: each run in it waits for a tick. ``limit`` runs (None: until
    ``close``) end the slot."""

    def __init__(self, limit: int | None, padding: bool = False) -> None:
        self.limit, self.started, self.closed, self.padding = limit, 0, False, padding
        self._tick = asyncio.Event()

    @property
    def over(self) -> bool:
        return self.closed or (self.limit is not None and self.started >= self.limit)

    def tick(self) -> None:
        self._tick.set()  # at most one tick waits unused: a late run never bunches them

    async def enter(self) -> None:
        await self._tick.wait()
        self._tick.clear()
        self.started += 1

    def close(self) -> None:
        self.closed = True


class Pacer:
    """Runs at ``rate`` per second in slots of ``runs`` (see the module docstring)."""

    def __init__(self, runner: AsyncSecureRunner, rate: float, runs: int,
                 depth: int = 1) -> None:
        if not rate > 0:
            raise ValueError(f"--rate: must be above 0, got {rate}")
        self.runner, self.interval, self.runs = runner, 1.0 / rate, runs
        self.depth = max(1, depth)  # frames under way at most, for padding to start one
        self.circuit: str | None = None  # the last real run's: what padding runs run
        self.padding_runs = 0
        self.padding_frames = 0
        self.padding_failed = 0  # padding frames whose runs failed (the stream goes on)
        self._waiting: deque[tuple[asyncio.Future, int | None]] = deque()
        self._ticker: asyncio.Task | None = None
        self._frames: set[Gate] = set()  # slots given to frames that have not closed them
        self._padding: set[asyncio.Task] = set()
        self._closing = False  # no new slot; the padding frame under way keeps its ticks

    def start(self) -> None:
        self._ticker = asyncio.get_running_loop().create_task(self._tick())

    async def slot(self, limit: int | None) -> Gate:
        """Wait for a slot of ``limit`` runs (None: until the gate is closed)."""
        future = asyncio.get_running_loop().create_future()
        self._waiting.append((future, limit))
        return await future

    async def _tick(self) -> None:
        loop = asyncio.get_running_loop()
        at = loop.time()
        while not self._closing:
            gate = self._next_gate()
            while True:
                if gate is not None:
                    gate.tick()
                at += self.interval
                await asyncio.sleep(max(0.0, at - loop.time()))
                if gate is None or gate.over or (self._closing and not gate.padding):
                    break

    def _next_gate(self) -> Gate | None:
        while self._waiting:
            future, limit = self._waiting.popleft()
            if not future.done():
                gate = Gate(limit)
                future.set_result(gate)
                self._frames.add(gate)
                return gate
        if self.circuit is None or self._under_way() >= self.depth:
            return None  # a tick without a run: the next one looks again
        gate = Gate(self.runs, padding=True)
        task = asyncio.get_running_loop().create_task(self._pad(gate, self.circuit))
        self._padding.add(task)
        task.add_done_callback(self._padded)
        return gate

    def _under_way(self) -> int:
        """Frames whose slot was given and whose runs are not all done, padding included."""
        self._frames = {gate for gate in self._frames if not gate.closed}
        return len(self._frames) + len(self._padding)

    def _padded(self, task: asyncio.Task) -> None:
        self._padding.discard(task)
        if not task.cancelled() and task.exception() is not None:
            self.padding_failed += 1  # its run's error was the runner's to retry or report

    async def _pad(self, gate: Gate, circuit_id: str) -> None:
        """A padding frame: the last frame's inputs again, and K runs on noise."""
        fixed = self.runner.fixed(circuit_id)
        n_inputs = registry.interface(circuit_id).n_inputs
        self.runner.expect(circuit_id, self.runs, fixed)
        self.padding_frames += 1
        for _ in range(self.runs):
            await gate.enter()
            await self.runner.invoke(circuit_id, _noise(n_inputs, fixed))
            self.padding_runs += 1

    async def close(self) -> None:
        """Start no slot more; the padding frame under way finishes its runs on its ticks
        (a run cut off would be a failed session in the servers' logs), then the ticks
        stop."""
        self._closing = True
        bound = 5 * self.runs * self.interval + 30
        for gate_task in list(self._padding):
            with contextlib.suppress(Exception):
                await asyncio.wait_for(gate_task, bound)
        if self._ticker is not None:
            self._ticker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._ticker
        for future, _ in self._waiting:
            future.cancel()


def _noise(n_inputs: int, fixed: FixedInputs | None) -> np.ndarray:
    """Random input bits, with the declared shared bits (their labels went ahead)."""
    bits = (np.frombuffer(os.urandom(n_inputs), np.uint8) & 1).astype(bool)
    if fixed is not None:
        bits[fixed.mask] = fixed.bits[fixed.mask]
    return bits


class ThreadedRunner:
    """``runner``'s loop in a thread of its own for a ``with`` block, and the blocking
    calls of a garbled backend for any number of threads at once. ``rate``: runs paced
    in slots of ``runs_per_slot``, ``depth`` frames under way at most (``Pacer``).
    ``runner`` itself must not be called until the block ends."""

    def __init__(self, runner: SecureRunner, rate: float | None = None,
                 runs_per_slot: int = 1, depth: int = 1) -> None:
        self.blocking, self.loop, self.secure = runner, runner.loop, runner.async_runner
        self.pacer = Pacer(self.secure, rate, runs_per_slot, depth) if rate else None
        # the last runs' figures (what the tracker sizes its frames in flight from);
        # bounded: a stream of an hour makes hundreds of thousands
        self.invocations_seen: deque[Invocation] = deque(maxlen=SEEN_RUNS)
        self._thread: threading.Thread | None = None
        self._calls: set[concurrent.futures.Future] = set()  # submitted, not yet done

    def __enter__(self) -> ThreadedRunner:
        self._thread = threading.Thread(target=self.loop.run_forever, name="snail-runner",
                                        daemon=True)
        self._thread.start()
        if self.pacer is not None:
            self.loop.call_soon_threadsafe(self.pacer.start)
        return self

    def __exit__(self, exc_type: type | None, *exc: object) -> None:
        try:
            if exc_type is not None:  # interrupted: the calls under way end now
                self.cancel_calls()
            if self.pacer is not None:
                self._submit(self.pacer.close())
        finally:
            self.loop.call_soon_threadsafe(self.loop.stop)
            if self._thread is not None:
                self._thread.join()

    def cancel_calls(self) -> None:
        """End every call under way (the stream was interrupted): their threads raise."""
        for call in list(self._calls):
            call.cancel()

    def _submit(self, coro: Coroutine) -> Any:
        call = asyncio.run_coroutine_threadsafe(coro, self.loop)
        self._calls.add(call)
        try:
            return call.result()
        finally:
            self._calls.discard(call)

    def slot(self, limit: int | None) -> Gate | None:
        """A slot of the pacer (None when runs are not paced): the calling thread waits
        for its turn."""
        return None if self.pacer is None else self._submit(self.pacer.slot(limit))

    def close_slot(self, gate: Gate | None) -> None:
        if gate is not None:
            self.loop.call_soon_threadsafe(gate.close)

    def invoke(self, circuit_id: str, input_bits: np.ndarray,
               gate: Gate | None = None, frame: bytes | None = None) -> Invocation:
        run = self._submit(self._invoke(circuit_id, input_bits, gate, frame))
        self.invocations_seen.append(run)
        return run

    async def _invoke(self, circuit_id: str, bits: np.ndarray, gate: Gate | None,
                      frame: bytes | None) -> Invocation:
        if gate is not None:
            await gate.enter()
        if self.pacer is not None:
            self.pacer.circuit = circuit_id
        return await self.secure.audits.named(self.secure.invoke(circuit_id, bits, frame))

    def expect(self, circuit_id: str, count: int, fixed: FixedInputs | None = None) -> None:
        async def announce() -> None:
            self.secure.expect(circuit_id, count, fixed)
            await asyncio.sleep(0)

        self._submit(announce())

    def fixed(self, circuit_id: str) -> FixedInputs | None:
        return self.secure.fixed(circuit_id)

    def use_frame(self, handle: bytes, map_owner: str, relay: str | None = None) -> None:
        async def use() -> None:
            self.secure.use_frame(handle, map_owner, relay)

        self._submit(use())

    @property
    def totals(self) -> dict[str, int]:
        return self.secure.totals

    @property
    def retries(self) -> int:
        return self.secure.retries

    @property
    def scheme(self) -> str:
        return self.secure.scheme

    @property
    def audits(self) -> Audits:
        """The runner's audits (audit.py); with frames in flight, a frame's counts taken
        before and after it include the runs of the frames beside it."""
        return self.secure.audits


class GatedRunner:
    """One frame's face of a ThreadedRunner: its runs wait for its slot's ticks."""

    def __init__(self, threaded: ThreadedRunner, gate: Gate | None) -> None:
        self.threaded, self.gate = threaded, gate

    def invoke(self, circuit_id: str, input_bits: np.ndarray,
               frame: bytes | None = None) -> Invocation:
        return self.threaded.invoke(circuit_id, input_bits, self.gate, frame)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.threaded, name)
