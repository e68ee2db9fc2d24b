"""Following a made-up camera privately at its rate (``snail-bench track``).

A sequence (snail_sim/sequences.py: the hand-held walk or Turbo's drive) is followed by
``Localizer.track``'s tracker on the fixed schedule, through the two servers (embedded on
loopback, or given), frames fed as fast as the tracker takes them or at a camera's rate
(``feed_fps``: frame i is captured at i / fps after the first localization is back, and a
tracker that falls behind takes the newest frame, dropping the others). Then, for every
frame, OpenCV's pose on the same matches: ``cv2.solvePnP`` (SOLVEPNP_ITERATIVE from the
previous frame's OpenCV answer) refined by ``cv2.solvePnPRefineLM`` to its tolerance
(converged), against which each tracked pose is measured: its RMS over OpenCV's, whether
it is within max(0.01 px, 1 %) of it, the rotation between them and the distance between
the camera centres over the median depth of the frame's points.

The timed part is the tracker alone (the sequence is made before, OpenCV runs after);
``client_cpu_s_per_frame`` is this process's CPU over it (building frames, labels, TLS,
decoding, the steps), beside ``opencv_cpu_s_per_frame``, OpenCV's own solve on the device.
"""

from __future__ import annotations

import json
import math
import statistics
import tempfile
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from snail_client.localize import GarbledBackend, Options, backend_for
from snail_client.owner_localize import session
from snail_client.track_frames import MapFrames, Problems
from snail_client.tracking import Item, Tracker, summary
from snail_common.loc.mapfile import Frame
from snail_common.loc.problem import PoseVectors, Problem, ProblemError
from snail_common.loc.reference import reprojection_rms
from snail_common.loc.trust import pose_error
from snail_sim.sequences import Sequence, make

ITERATIVE_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-12)
WITHIN_PX, WITHIN_REL = 0.01, 0.01


@dataclass
class Feed:
    """The frames as a camera gives them: all, as fast as they are taken (``fps`` None),
    or captured at ``fps`` from the moment the second frame is asked for (the first
    localization is back), the newest one taken when the tracker falls behind."""

    sequence: Sequence
    fps: float | None
    odometry: bool = False
    captured: dict[int, float] = field(default_factory=dict)  # frame -> capture time
    dropped: int = 0

    def items(self) -> Iterator[Item]:
        problems, index, clock = self.sequence.problems, 0, None
        while index < len(problems):
            now = time.perf_counter()
            if self.fps and index > 0:
                if clock is None:
                    clock = now - index / self.fps
                newest = int((now - clock) * self.fps)
                if newest > index:
                    self.dropped += min(newest, len(problems)) - index
                    index = newest
                    if index >= len(problems):
                        return
                capture = clock + index / self.fps
                if capture > now:
                    time.sleep(capture - now)
                    now = capture
            self.captured[index] = now
            yield Item(str(index), self.source(index), self.motion(index))
            index += 1

    def source(self, index: int) -> Problem | Frame | ProblemError:
        problem = self.sequence.problems[index]
        return problem if problem is not None else ProblemError("no point in view")

    def motion(self, index: int) -> PoseVectors | None:
        motions = self.sequence.motions
        return motions[index] if self.odometry and motions else None


class OwnerFeed(Feed):
    """The same frames as the map-owner setting's snail-frame/1: the map ids of their
    points (the map is the sequence's world, ids 1..M)."""

    def source(self, index: int) -> Frame | ProblemError:
        problem = self.sequence.problems[index]
        if problem is None:
            return ProblemError("no point in view")
        return Frame(K=problem.K, dist=problem.dist, points2d=problem.points2d,
                     map_ids=self.sequence.ids[index] + 1, initial_pose=problem.initial_pose,
                     image_size=problem.image_size)


def opencv_converged(problem: Problem, start: PoseVectors) -> PoseVectors:
    """OpenCV's converged pose from ``start``: iterative solvePnP from it, then LM to
    its tolerance."""
    rvec, tvec = start.rvec.reshape(3, 1).copy(), start.tvec.reshape(3, 1).copy()
    _, rvec, tvec = cv2.solvePnP(problem.points3d, problem.points2d, problem.K, problem.dist,
                                 rvec, tvec, useExtrinsicGuess=True,
                                 flags=cv2.SOLVEPNP_ITERATIVE)
    rvec, tvec = cv2.solvePnPRefineLM(problem.points3d, problem.points2d, problem.K,
                                      problem.dist, rvec, tvec, ITERATIVE_CRITERIA)
    return PoseVectors(rvec.reshape(3), tvec.reshape(3))


def compare(problem: Problem, tracked: PoseVectors, opencv: PoseVectors) -> dict:
    """One frame's tracked pose against OpenCV's converged one."""
    rms = reprojection_rms(problem, tracked.rvec, tracked.tvec)
    rms_cv = reprojection_rms(problem, opencv.rvec, opencv.tvec)
    err = pose_error(tracked.rvec, tracked.tvec, opencv)
    depth = problem.points3d @ cv2.Rodrigues(opencv.rvec)[0].T + opencv.tvec
    truth = problem.reference_pose
    return {"rms": rms, "rms_opencv": rms_cv, "rms_ratio": rms / rms_cv if rms_cv else math.inf,
            "within": rms <= rms_cv + max(WITHIN_PX, WITHIN_REL * rms_cv),
            "deg": err["rotation_deg"],
            "rel": err["translation"] / float(np.median(depth[:, 2])),
            # how far each is from the made-up camera's true pose: where OpenCV's own pose
            # is far from it (one small tag in view), agreeing with OpenCV means little
            "truth_deg": pose_error(tracked.rvec, tracked.tvec, truth)["rotation_deg"],
            "opencv_truth_deg": pose_error(opencv.rvec, opencv.tvec, truth)["rotation_deg"]}


def opencv_answers(sequence: Sequence, frames: list[int]) -> tuple[dict, float]:
    """OpenCV's converged pose of each of ``frames`` (each from its previous answer), and
    its CPU seconds per frame."""
    answers: dict[int, PoseVectors] = {}
    last: PoseVectors | None = None
    cpu = time.process_time()
    for index in frames:
        problem = sequence.problems[index]
        if problem is None:
            continue
        last = opencv_converged(problem, last or problem.initial_pose
                                or problem.reference_pose)
        answers[index] = last
    return answers, (time.process_time() - cpu) / max(len(answers), 1)


def track_run(sequence: Sequence, options: Options, feed_fps: float | None = None,
              map_points: int | None = None, odometry: bool = False) -> dict:
    """Follow ``sequence``; the FORMATS.md round-4 entry (and ``per_frame`` for the
    figure)."""
    owner = map_points is not None
    feed = (OwnerFeed if owner else Feed)(sequence, feed_fps, odometry)
    with tempfile.TemporaryDirectory(prefix="snail-bench-track-") as tmp, \
            _tracker(options, sequence, owner, Path(tmp)) as tracker:
        records, outs = [], []
        began, cpu = time.perf_counter(), time.process_time()
        for out, _ in tracker.run(feed.items()):
            outs.append(time.perf_counter())
            records.append(out)
        wall, cpu = time.perf_counter() - began, time.process_time() - cpu
        engine = _engine(tracker.backend)
        ot = _ot(tracker, len(records)) if owner else None
        link = tracker.frames.link if owner else None
        relayed = link is not None and link.relay is not None  # through the evaluator
    totals = summary(records, wall, cpu, tracker)
    report = _report(sequence, options, feed, records, outs, totals, engine, owner)
    if owner:
        report.update(ot=ot, relay=relayed)
    return report


def _report(sequence: Sequence, options: Options, feed: Feed, records: list[dict],
            outs: list[float], totals: dict, engine: str | None, owner: bool) -> dict:
    indices = [int(r["input"]) for r in records]
    latencies = [out - feed.captured[i] for out, i in zip(outs, indices)]
    answers, cv_cpu = opencv_answers(sequence, indices)
    rows, per_frame = [], []
    for index, out, latency in zip(indices, records, latencies):
        problem = sequence.problems[index]
        row = None
        if problem is not None and "rvec" in out and index in answers:
            row = compare(problem, PoseVectors(np.array(out["rvec"]), np.array(out["tvec"])),
                          answers[index])
            rows.append(row)
        per_frame.append({"frame": index, "latency_s": latency, "runs": out["runs"],
                          "track_status": out["track_status"],
                          "rms_ratio": row["rms_ratio"] if row else None})
    after = outs[-1] - outs[0] if len(outs) > 1 else 0.0
    lat = np.percentile(latencies, [50, 95]) if latencies else [math.nan] * 2
    schemes = Counter(r.get("scheme") for r in records if r.get("scheme"))
    tables = [r["traffic"]["garbler_to_evaluator"] for r in records[1:] if "traffic" in r]
    points = next((r["circuit"]["points"] for r in records if "circuit" in r),
                  options.circuit_points(max((p.n for p in sequence.problems if p), default=0)))
    return {
        "points": points, "frames": len(records), "sequence": sequence.name,
        "fps": totals["fps"],
        "fps_after_first": round((len(outs) - 1) / after, 3) if after else None,
        "latency_s": {"p50": round(float(lat[0]), 5), "p95": round(float(lat[1]), 5),
                      "max": round(max(latencies), 5) if latencies else None},
        "runs_per_frame": options.runs_per_frame, "lost": totals["lost"],
        "rms_ratio": {"median": _r(statistics.median(r["rms_ratio"] for r in rows)),
                      "max": _r(max(r["rms_ratio"] for r in rows))} if rows else None,
        "within": _r(sum(r["within"] for r in rows) / len(rows)) if rows else None,
        "pose_error": {"deg_max": _r(max(r["deg"] for r in rows)),
                       "rel_max": _r(max(r["rel"] for r in rows))} if rows else None,
        "truth_deg": {who: {"median": _r(statistics.median(r[key] for r in rows)),
                            "max": _r(max(r[key] for r in rows))}
                      for who, key in (("tracked", "truth_deg"), ("opencv", "opencv_truth_deg"))
                      } if rows else None,
        "link_bound_fps": None, "dropped": feed.dropped,
        "setting": "map-owner" if owner else "offload",
        "client_cpu_s_per_frame": totals["client_cpu_s_per_frame"],
        "opencv_cpu_s_per_frame": round(cv_cpu, 6),
        "scheme": schemes.most_common(1)[0][0] if schemes else None, "engine": engine,
        "in_flight": totals["in_flight"], "feed_fps": feed.fps, "rate": options.rate,
        "revealed": totals["revealed"], "runs_first_frame": totals["runs_first_frame"],
        "circuit": totals["circuit"], "wall_s": totals["wall_s"],
        "table_bytes_per_frame": int(statistics.median(tables)) if tables else None,
        "per_frame": per_frame,
    }


def _r(x: float) -> float:
    return round(float(x), 6)


class _tracker:
    """A tracker on a backend for the ``with`` block: the offload setting's, or with a
    map owner (started here, the sequence's world as its map) the map-owner setting's."""

    def __init__(self, options: Options, sequence: Sequence, owner: bool, tmp: Path) -> None:
        self.options, self.sequence, self.owner, self.tmp = options, sequence, owner, tmp

    def __enter__(self) -> Tracker:
        if self.owner:
            path = self.tmp / "map.json"
            path.write_text(json.dumps({"format": "snail-map/1", "points": [
                {"id": i + 1, "xyz": p.tolist()} for i, p in enumerate(self.sequence.world)]}))
            self._ctx = session(self.options, None, str(path))
            backend, link, known = self._ctx.__enter__()
            return Tracker(self.options, backend, MapFrames(self.options, link, known))
        self._ctx = backend_for(self.options)
        return Tracker(self.options, self._ctx.__enter__(), Problems(self.options))

    def __exit__(self, *exc: object) -> None:
        self._ctx.__exit__(*exc)


def _ot(tracker: Tracker, frames: int) -> dict | None:
    """The map-owner setting's OT figures (FORMATS.md, round 5): runs whose session's OT
    was done before the run began, runs that took a pad correction, and the device's
    time a frame on the map owner's account (selection and corrections)."""
    secure = getattr(tracker.backend, "secure", None)
    owner = getattr(getattr(secure, "async_runner", None), "owner", None)
    link = tracker.frames.link
    if owner is None or owner.frame is None or link is None:
        return None
    return {"precomputed": owner.precomputed, "used": owner.used,
            "per_frame_s": round((link.select_s + owner.seconds) / max(frames, 1), 6)}


def _engine(backend: object) -> str | None:
    """The garbling engine the daemons serve with (their /health)."""
    if not isinstance(backend, GarbledBackend):
        return None
    try:
        return backend.secure.health("garbler").get("engine")
    except Exception:  # a health probe that fails says nothing of the run
        return None


def track_report(points: tuple[int, ...], frames: int, sequence: str, options: Options,
                 feed_fps: float | None = None, map_points: int | None = None,
                 odometry: bool = False, seed: int = 1) -> dict:
    """``{"track": {circuit id: entry}}`` (FORMATS.md, round 4), one entry per n."""
    report: dict[str, dict] = {}
    for n in points:
        rng = np.random.default_rng(seed)
        kw = {"map_points": map_points} if map_points and sequence == "handheld" else {}
        made = make(sequence, rng, n, frames, **kw)
        entry = track_run(made, _sized(options, n, sequence), feed_fps, map_points, odometry)
        circuit = entry["circuit"] or f"n{n}"  # as the servers name it: loc/<id>
        report[circuit.split("/", 1)[-1]] = entry
    return {"track": report}


def _sized(options: Options, n: int, sequence: str) -> Options:
    """Turbo's frames see 2-4 tags: padded to n points, one circuit for all of them."""
    import dataclasses

    return dataclasses.replace(options, pad_points=n) if sequence == "turbo" else options
