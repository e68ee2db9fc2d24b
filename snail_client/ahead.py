"""Garble-ahead on the client: sessions prepared before their inputs exist.

Garbling does not depend on inputs, so a caller that knows invocations of a circuit are
coming (``expect``: a padded frame makes at least ``--min-invocations``) lets the pool
keep up to ``ahead`` sessions prepared, the next one garbled while the current one is
evaluated. A prepared session is used once or cancelled, never reused; one prepared for
other shared input bits (``FixedInputs``) or whose link broke is cancelled when found and
a fresh one is garbled.

A runner localizing a sequence (a second frame of a circuit was declared) keeps its
depth garbled between frames too, for the circuit of its last frame only (a frame of
another circuit cancels them): sessions beyond the current frame's invocations are
prepared without a frame's labels, and the next frame's ``expect`` sends its labels for
them. Without that, each frame's first invocation waited for a whole garbling and its
trip across the server link (about 0.1 s of a 1.2 s localization under `region`).

Sessions prepared ahead are *reservations* to the servers (``ahead`` in their requests):
they yield their place to another client's live session when a server is full
(snail_common/net/slots.py). A reservation refused as busy or evicted tells the pool that
it holds more than the servers can spare: its depth drops by one at once (to none at
all, where every run then garbles when it is needed) and grows back by one only after
``REGROW_AFTER`` invocations without another refusal.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Awaitable, Callable

import numpy as np

from snail_common.net.linkrates import MAX_AHEAD

from .sessions import FixedInputs, Prepared

REGROW_AFTER = 20  # invocations without a refusal before the pool may hold one more


class AheadPool:
    """Prepared sessions by circuit id. ``prepare(circuit_id)`` asks the servers for a new
    one (with the declared fixed inputs' labels); ``cancel(session)`` drops one."""

    def __init__(self, ahead: int, prepare: Callable[[str, bool], Awaitable[Prepared]],
                 cancel: Callable[[Prepared], None],
                 adopt: Callable[[Prepared, FixedInputs], bool]) -> None:
        self.ahead = ahead  # the depth wanted (the runner sizes it from the link)
        self._most = max(ahead, MAX_AHEAD)
        self.ceiling = self._most  # the depth the servers' refusals allow (module doc)
        self._calm = 0  # invocations since the last refusal
        self._prepare = prepare  # (circuit id, with the declared fixed inputs' labels)
        self._cancel = cancel
        self._adopt = adopt  # sends a frame's fixed labels for a session prepared without
        self._frames: dict[str, int] = {}  # frames declared per circuit id
        self._warm: str | None = None  # the circuit of the last frame: kept warm alone
        self._prepared: dict[str, deque[Prepared]] = {}
        self._expected: dict[str, int] = {}
        self._fixed: dict[str, FixedInputs | None] = {}
        # the frame before the current one, while its runs are still coming (frames in
        # flight): its shared inputs and how many runs it has left
        self._unfinished: dict[str, tuple[FixedInputs, int]] = {}
        self._filling: set[asyncio.Task] = set()

    def expect(self, circuit_id: str, count: int, fixed: FixedInputs | None = None) -> None:
        """At least ``count`` invocations of ``circuit_id`` are coming: keep up to
        ``ahead`` of them prepared (garbled) before they are needed, with the labels of
        the ``fixed`` input bits they share already at the evaluator."""
        left, before = self._expected.get(circuit_id, 0), self._fixed.get(circuit_id)
        if left > 0 and before is not None and not FixedInputs.same(before, fixed):
            self._unfinished[circuit_id] = (before, left)  # its runs still to come
        self._fixed[circuit_id] = fixed
        self._frames[circuit_id] = self._frames.get(circuit_id, 0) + 1
        if self._warm not in (None, circuit_id):  # another circuit now (a new n): its
            self._drop_warm(self._warm)  # sessions kept between frames would only linger
        self._warm = circuit_id
        queue = self._prepared.get(circuit_id, deque())
        # sessions kept garbled between frames take this frame's labels only as many as
        # its runs need: the others stay warm for the next frame (a frame of one run
        # would otherwise spend one and see the rest cancelled by the next frame)
        needed = max(count, 0) - sum(FixedInputs.same(x.fixed, fixed) for x in queue)
        unfinished = self._unfinished.get(circuit_id, (None, 0))[0]
        for session in [x for x in queue if not FixedInputs.same(x.fixed, fixed)]:
            if unfinished is not None and FixedInputs.same(session.fixed, unfinished):
                continue  # the frame before still has runs to make with it
            if session.fixed is None and session.usable and needed <= 0:
                continue  # warm, and not needed by this frame
            if session.fixed is None and fixed is not None and self._adopt(session, fixed):
                needed -= 1
                continue  # kept garbled between frames: this frame's labels went now
            queue.remove(session)  # prepared for other shared bits: of no use now
            self._cancel(session)
        ready = [x for x in queue if FixedInputs.same(x.fixed, fixed)]  # taken first
        warm = [x for x in queue if not FixedInputs.same(x.fixed, fixed)]
        queue.clear()
        queue.extend(ready + warm)
        self._expected[circuit_id] = max(count, 0)
        self.fill(circuit_id)

    def fixed(self, circuit_id: str) -> FixedInputs | None:
        """The input bits ``expect`` last declared shared by ``circuit_id``'s runs."""
        return self._fixed.get(circuit_id)

    @property
    def depth(self) -> int:
        """Sessions kept prepared: as many as wanted, as few as the servers allow."""
        return min(self.ahead, self.ceiling)

    def refused(self) -> None:
        """A server refused a reservation (busy) or took one back (evicted): hold one
        fewer, and wait before holding more again."""
        self.ceiling = max(0, min(self.ceiling, self.ahead) - 1)
        self._calm = 0

    def used(self, circuit_id: str) -> None:
        """One of the expected invocations of ``circuit_id`` is under way."""
        self._expected[circuit_id] = max(self._expected.get(circuit_id, 0) - 1, 0)
        self._calm += 1
        if self._calm >= REGROW_AFTER and self.ceiling < self._most:
            self.ceiling += 1
            self._calm = 0

    def take(self, circuit_id: str, bits: np.ndarray) -> Prepared | None:
        """A prepared session of ``circuit_id`` the servers still hold and that fits
        ``bits`` (its fixed inputs' labels were sent for these values): one holding this
        run's shared labels first, else one kept warm. Sessions no run can use any more
        go (cancelled); those of another frame still under way stay for it (frames in
        flight). A map-owner session serves any frame: the map owner's share is bound to
        the frame only when it runs (snail_mapd/pads.py). A session whose tables the
        evaluator found changed is handed over, to fail its run: that is not a failure
        to pass over in silence (a link that changes bytes, or a garbler)."""
        queue = self._prepared.get(circuit_id)
        if not queue:
            return None
        for session in [x for x in queue if not x.usable]:
            queue.remove(session)
            if session.tables_changed:  # changed on the server link while garbled ahead:
                return session  # the run fails on the evaluator's word, naming the link
            if session.refused:
                self.refused()
            self._cancel(session)  # expired or evicted
        fits = [x for x in queue if x.fixed is None or x.fixed.matches(bits)]
        if not fits:
            return None
        session = next((x for x in fits if x.fixed is not None), fits[0])
        queue.remove(session)
        self._took(circuit_id, session)
        return session

    def _took(self, circuit_id: str, session: Prepared) -> None:
        """Count a run of the frame before the current one, still under way; once its
        runs are all taken, the sessions left with its labels go."""
        unfinished = self._unfinished.get(circuit_id)
        if unfinished is None or not FixedInputs.same(session.fixed, unfinished[0]):
            return
        fixed, left = unfinished[0], unfinished[1] - 1
        if left > 0:
            self._unfinished[circuit_id] = (fixed, left)
            return
        del self._unfinished[circuit_id]
        queue = self._prepared.get(circuit_id, deque())
        for other in [x for x in queue if FixedInputs.same(x.fixed, fixed)]:
            queue.remove(other)
            self._cancel(other)

    async def in_flight(self, circuit_id: str, bits: np.ndarray) -> Prepared | None:
        """Wait for a session of ``circuit_id`` already being prepared, rather than ask
        the garbler for yet another one (it would garble it behind those)."""
        tasks = [t for t in self._filling if t.get_name() == circuit_id]
        if not tasks:
            return None
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        return self.take(circuit_id, bits)

    def fill(self, circuit_id: str) -> None:
        """Prepare sessions in the background up to min(ahead, expected invocations), or
        up to ``ahead`` in a sequence of frames: those beyond the frame's invocations
        without its labels."""
        queue = self._prepared.setdefault(circuit_id, deque())
        frame_left = self._expected.get(circuit_id, 0)
        sequence = self._frames.get(circuit_id, 0) > 1 and circuit_id == self._warm
        want = self.depth if sequence else min(self.depth, frame_left)
        pending = len(queue) + sum(1 for t in self._filling if t.get_name() == circuit_id)
        for i in range(pending, want):
            task = asyncio.get_running_loop().create_task(
                self._prepare(circuit_id, i < frame_left), name=circuit_id)
            self._filling.add(task)
            task.add_done_callback(self._prepared_one)

    def _prepared_one(self, task: asyncio.Task) -> None:
        self._filling.discard(task)
        if not task.cancelled() and task.exception() is None:
            name, session = task.get_name(), task.result()
            queue = self._prepared.setdefault(name, deque())
            if session.fixed is None and not self._can_serve(name, queue, session):
                self._cancel(session)
                return
            queue.append(session)
        # a failed preparation is not an error yet: the invocation that needs one
        # prepares again and reports what breaks

    def _can_serve(self, name: str, queue: deque, session: Prepared) -> bool:
        """Whether a session garbled without a frame's labels still has a frame to serve:
        kept warm for the last frame's circuit, or taking the labels of the frame now
        expected where its queue lacks sessions that have them (asked for before the
        frame came). Not when its circuit has been left since."""
        expected = self._expected.get(name, 0)
        if not expected:
            return name == self._warm
        fixed = self._fixed.get(name)
        if fixed is None or sum(x.fixed is not None for x in queue) >= expected:
            return True
        return self._adopt(session, fixed)

    def _drop_warm(self, circuit_id: str) -> None:
        """Cancel the sessions of ``circuit_id`` kept garbled without a frame's labels."""
        queue = self._prepared.get(circuit_id, deque())
        for session in [x for x in queue if x.fixed is None]:
            queue.remove(session)
            self._cancel(session)

    async def close(self) -> None:
        """Stop preparing and cancel every prepared session."""
        for task in list(self._filling):
            task.cancel()
        await asyncio.gather(*self._filling, return_exceptions=True)
        for queue in self._prepared.values():
            for session in queue:
                self._cancel(session)
        self._prepared.clear()
