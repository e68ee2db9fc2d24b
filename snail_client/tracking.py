"""Following a stream of frames on the fixed schedule: ``snail-client track`` and
``Localizer.track`` both stand on ``Tracker``.

The schedule (snail_common/loc/schedule.py) decides each frame's runs and start; the
frame's own work is a solver's (``Problems``: the device holds its 2D-3D matches;
``MapFrames``: the map-owner setting); here they meet the backend:

- every frame is built (read, tags detected) and solved in a worker thread, up to
  ``in_flight`` frames at once on a garbled backend, whose runs go concurrently over the
  same connections (threaded.py); a frame starts from the prediction the schedule has
  when it starts, so with D > 1 that is the pose of the frame D before it;
- answers are taken in frame order: the schedule observes each and the frame's record
  gets ``runs``, ``latency_s`` (handed in to pose out), ``track_status`` and
  ``revealed`` (FORMATS.md, round 4);
- a frame with nothing to run (it cannot be read, no tag in view, degenerate points)
  still makes its K runs: padding on the last frame's circuit and inputs, so the servers
  see a frame like any other;
- ``rate``: runs paced at R per second whatever the frames (threaded.Pacer).

Local backends (cleartext, float64: no servers) solve one frame at a time in the
caller's thread.
"""

from __future__ import annotations

import concurrent.futures
import copy
import math
import queue
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from snail_common.loc.backends import Backend
from snail_common.loc.mapfile import Frame
from snail_common.loc.problem import PoseVectors, Problem, ProblemError
from snail_common.loc.schedule import Outcome, Plan, Schedule
from snail_common.loc.trust import TRUSTED
from snail_common.pnp.spec import Spec

from .audit import IntegrityFailure
from .links import ServiceError
from .localize import (
    GarbledBackend,
    Options,
)
from .threaded import Gate, GatedRunner, ThreadedRunner
from .track_frames import MapFrames, Problems, Solved

Source = Problem | Frame | Exception | Callable[[], Any]


@dataclass(frozen=True)
class Item:
    """A frame handed to the tracker: its name, what it is built from (a problem, a
    map-owner frame, the error that made it unreadable, or a callable building one in the
    worker) and the camera's motion since the previous frame, if the caller knows it."""

    name: str
    source: Source
    motion: PoseVectors | None = None


class _FrameBackend(GarbledBackend):
    """A garbled backend for one frame of a stream: its own byte counts, over a runner
    that other frames use at the same time."""

    def __init__(self, runner: GatedRunner) -> None:
        super().__init__(runner)
        self._bytes: dict[str, int] = {}

    def _secure_run(self, circuit_id: str, bits: np.ndarray) -> np.ndarray:
        run = self.secure.invoke(circuit_id, bits, self.frame)
        self.schemes[run.scheme] += 1
        for link, count in run.traffic.items():
            self._bytes[link] = self._bytes.get(link, 0) + count
        return run.outputs

    def traffic(self) -> dict[str, int]:
        return dict(self._bytes)


class Tracker:
    """A stream on the fixed schedule over ``backend``; ``frames`` solves each frame."""

    def __init__(self, options: Options, backend: Backend, frames: Problems | MapFrames) -> None:
        self.options, self.backend, self.frames = options, backend, frames
        do = options.mode == "do"
        self.schedule = Schedule(1 if do else options.runs_per_frame,
                                 1 if do else options.min_invocations,
                                 options.on_lost, options.motion_model, frames.warmup)
        self.in_flight = 1
        self.padding_frames = 0  # frames that made padding runs only (nothing to run)
        self.paced_padding_runs = 0  # --rate: runs in slots no frame took
        self.paced_padding_failed = 0  # --rate: padding frames whose runs failed
        self._spec: Spec | None = None  # the last circuit run: what padding runs run
        self._threaded: ThreadedRunner | None = None
        self._index = 0  # the next frame's

    @property
    def garbled(self) -> bool:
        return isinstance(self.backend, GarbledBackend)

    def run(self, items: Iterable[Item]) -> Iterator[tuple[dict, Any]]:
        """(record, what the frame was built into) per frame, in frame order."""
        if not self.garbled:
            if (self.options.in_flight or 1) == 1:
                yield from self._sequential(iter(items), None)
                return
            with concurrent.futures.ThreadPoolExecutor(self.frames.max_in_flight,
                                                       "snail-frame") as pool:
                source = iter(items)
                yield from self._sequential(source, None, until_tracking=True)
                yield from self._overlapped(source, pool)
            return
        th = ThreadedRunner(self.backend.secure, self.options.rate,
                            self.schedule.runs_per_frame, self.frames.max_in_flight)
        try:
            with th, concurrent.futures.ThreadPoolExecutor(self.frames.max_in_flight,
                                                           "snail-frame") as pool:
                self._threaded = th
                try:
                    source = iter(items)
                    yield from self._sequential(source, pool, until_tracking=True)
                    if self.in_flight > 1:
                        yield from self._overlapped(source, pool)
                    else:
                        yield from self._sequential(source, pool)
                except BaseException:
                    th.cancel_calls()  # interrupted: the frames under way end now
                    raise
        finally:
            self._threaded = None
            if th.pacer is not None:  # counted once the pacer stopped: the padding
                self.paced_padding_runs = th.pacer.padding_runs  # frame it ended included
                self.paced_padding_failed = th.pacer.padding_failed

    def _sequential(self, source: Iterator[Item], pool: concurrent.futures.Executor | None,
                    until_tracking: bool = False) -> Iterator[tuple[dict, Any]]:
        """One frame at a time, each pulled after the previous one's answer was taken
        (a closed loop, Turbo's, needs that); ``until_tracking``: only the padded first
        frames, then choose how many frames may be in flight."""
        while not until_tracking or self.schedule.waits_for_answers:
            item = next(source, None)
            if item is None:
                return
            handed_in = time.perf_counter()
            yield self._finish(*self._submit(pool, item, handed_in))
        self._choose_in_flight()

    def _overlapped(self, source: Iterator[Item], pool: concurrent.futures.Executor
                    ) -> Iterator[tuple[dict, Any]]:
        """Up to ``in_flight`` frames at once. The frames are pulled by a reader thread
        (the caller's iterator may wait for a camera), so an answer goes out the moment
        it and those before it are in, not when the next frame comes; a new frame is
        pulled when one in flight has been given back to the caller."""
        events: queue.Queue = queue.Queue()
        room = threading.Semaphore(self.in_flight)
        stop = threading.Event()

        def read() -> None:
            try:
                while room.acquire() and not stop.is_set():
                    item = next(source, None)
                    events.put(("item", item, time.perf_counter()))
                    if item is None:
                        return
            except BaseException as exc:  # the caller's iterator failed: raise it there
                events.put(("error", exc, 0.0))

        reader = threading.Thread(target=read, name="snail-frames", daemon=True)
        reader.start()
        pending: deque[tuple[Item, Plan, float, concurrent.futures.Future]] = deque()
        ended = False
        try:
            while not ended or pending:
                while pending and pending[0][3].done():
                    yield self._finish(*pending.popleft())
                    room.release()
                if ended and not pending:
                    break
                kind, item, handed_in = events.get()
                if kind == "error":
                    raise item
                if kind == "item" and item is None:
                    ended = True
                elif kind == "item":
                    pending.append(self._submit(pool, item, handed_in, events))
        finally:
            stop.set()
            room.release()

    def _submit(self, pool: concurrent.futures.Executor | None, item: Item,
                handed_in: float, events: queue.Queue | None = None
                ) -> tuple[Item, Plan, float, concurrent.futures.Future]:
        """Plan the frame and start it (in the caller's thread without a pool); a done
        frame puts an event in ``events``."""
        plan = self.schedule.plan(self._index, item.motion, 1 if pool is None
                                  else self.in_flight)
        self._index += 1
        if pool is None:
            done: concurrent.futures.Future = concurrent.futures.Future()
            done.set_result(self._frame(item, plan))
        else:
            done = pool.submit(self._frame, item, plan, False)
            if events is not None:
                done.add_done_callback(lambda _: events.put(("done", None, 0.0)))
        return item, plan, handed_in, done

    def _choose_in_flight(self) -> None:
        """--in-flight, or from the first frame's runs (``in_flight_for``)."""
        if self.options.in_flight is not None or self._threaded is None:
            self.in_flight = self.options.in_flight or 1
        else:
            self.in_flight = in_flight_for(list(self._threaded.invocations_seen))
        self.in_flight = max(1, min(self.in_flight, self.frames.max_in_flight))

    def _backend_for(self, gate: Gate | None, alone: bool) -> Backend:
        """A frame's backend: its own counts over the shared runner (garbled), a copy
        of a local one when frames overlap, else the tracker's."""
        if self._threaded is not None:
            return _FrameBackend(GatedRunner(self._threaded, gate))
        if alone:
            return self.backend
        backend = copy.copy(self.backend)
        backend.invocations = 0
        return backend

    def _frame(self, item: Item, plan: Plan, alone: bool = True) -> Solved:
        """Build and solve one frame (a worker thread's job; ``alone``: no other frame
        runs at the same time)."""
        built: Any = None
        try:
            built = item.source() if callable(item.source) else item.source
            if isinstance(built, Exception):
                raise built
        except ProblemError as exc:
            return self._padded(plan, str(exc))
        threaded = self._threaded
        gate = None if threaded is None else threaded.slot(None if plan.padded else plan.runs)
        try:
            backend = self._backend_for(gate, alone)
            try:
                solved = self.frames.solve(built, plan, backend)
            except ProblemError as exc:
                solved = Solved({"failure": str(exc), "invocations": 0}, None, None, False,
                                 built)
            except ServiceError as exc:  # the frame's runs failed: the stream goes on
                failed = {"failure": str(exc), "service_error": True, "invocations": 0}
                if isinstance(exc, IntegrityFailure):  # who is to blame (audit.py)
                    failed["error"] = exc.record()
                return Solved(failed, None, None, False, built)
            if solved.record.get("invocations", 0) == 0:  # degenerate: nothing ran
                solved.record["invocations"] = self._pad(plan, backend)
            else:
                self._spec = solved.spec
        finally:
            if threaded is not None:
                threaded.close_slot(gate)
        return solved

    def _padded(self, plan: Plan, failure: str) -> Solved:
        """A frame that could not be built: its runs on padding, in a slot if paced."""
        threaded = self._threaded
        if threaded is None:
            return Solved({"failure": failure, "invocations": self._pad(plan, self.backend)},
                           None, None, False)
        gate = threaded.slot(plan.runs)
        try:
            runs = self._pad(plan, _FrameBackend(GatedRunner(threaded, gate)))
        finally:
            threaded.close_slot(gate)
        return Solved({"failure": failure, "invocations": runs}, None, None, False)

    def _pad(self, plan: Plan, backend: Backend) -> int:
        """The frame's K runs as padding on the last circuit (none before the first)."""
        if self._spec is None or not isinstance(backend, GarbledBackend):
            return 0
        backend.pad_frame(self._spec, plan.runs)
        self.padding_frames += 1
        return plan.runs

    def _finish(self, item: Item, plan: Plan, handed_in: float,
                done: concurrent.futures.Future) -> tuple[dict, Any]:
        solved: Solved = done.result()
        out = {"frame": plan.index, "input": item.name, **solved.record}
        trusted = out.get("status") in TRUSTED
        seen = self.schedule.observe(plan, Outcome(
            trusted, solved.pose, int(out.get("invocations", 0)),
            solved.spec.registry_id if solved.spec is not None else None, solved.improved))
        out.update(runs=int(out.get("invocations", 0)),
                   latency_s=round(time.perf_counter() - handed_in, 5),
                   track_status=seen.track_status, revealed=seen.revealed,
                   prediction=plan.prediction)
        return out, solved.built


def in_flight_for(runs: list) -> int:
    """Frames in flight that keep the servers busy through the client's round trip: 1 +
    the median round trip (a run's wall time less its evaluation) over the median
    servers' part (the longest of garbling, evaluation and the tables' time on the
    server link at the rate the garbler measured last: its first estimates run low).
    That part is what a stream of runs is paced by at best; more frames in flight would
    only queue, each started from an older pose. On loopback: 1; under the lab's region
    profile (40 ms client round trip, 37 ms of tables a run at n = 6): 2."""
    if not runs:
        return 1
    link = runs[-1].timing.get("garbler_link_mbit", 0.0)
    served = [_served(r, link) for r in runs]
    if not max(served) > 0:
        return 1
    trip = float(np.median([r.wall_s - r.timing.get("evaluator_evaluate_s", 0.0)
                            for r in runs]))
    return 1 + max(0, math.floor(trip / float(np.median(served))))


def _served(run: Any, link_mbit: float) -> float:
    """The servers' part of one run: garbling, evaluation or the tables on the link."""
    t = run.timing
    tables = (run.traffic.get("garbler_to_evaluator", 0) * 8 / (link_mbit * 1e6)
              if link_mbit else 0.0)
    return max(t.get("evaluator_evaluate_s", 0.0), t.get("garbler_garble_s", 0.0), tables)


def summary(records: list[dict], wall_s: float, cpu_s: float, tracker: Tracker) -> dict:
    """The stream's summary (FORMATS.md, round 4): frames, fps, latency, runs per frame,
    frames lost and revealed, and what the servers could see."""
    latencies = [r["latency_s"] for r in records if "latency_s" in r]
    runs = [r.get("runs", 0) for r in records]
    p = np.percentile(latencies, [50, 95]) if latencies else (math.nan, math.nan)
    schedule = tracker.schedule
    return {
        "frames": len(records), "fps": round(len(records) / wall_s, 3) if wall_s else None,
        "latency_s": {"p50": round(float(p[0]), 5), "p95": round(float(p[1]), 5),
                      "max": round(max(latencies), 5) if latencies else None},
        "runs_per_frame": schedule.runs_per_frame,
        "runs_first_frame": runs[0] if runs else 0,
        "runs_after_first": sorted(set(runs[1:])),
        "lost": sum(r.get("track_status") == "lost" for r in records),
        "relocalized": sum(r.get("track_status") == "relocalized" for r in records),
        "revealed": sum(bool(r.get("revealed")) for r in records),
        "predictions": dict(Counter(r["prediction"] for r in records
                                    if r.get("prediction"))),
        "padding_frames": tracker.padding_frames,
        "paced_padding_runs": tracker.paced_padding_runs,
        "paced_padding_failed": tracker.paced_padding_failed,
        "in_flight": tracker.in_flight, "rate": tracker.options.rate,
        "circuit": schedule.circuit, "wall_s": round(wall_s, 4),
        "client_cpu_s_per_frame": round(cpu_s / len(records), 5) if records else None,
    }
