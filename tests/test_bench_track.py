"""``snail-bench track``'s measuring: the sequences it makes, the camera feed that drops
what a slow tracker cannot take, OpenCV's converged pose as the oracle and the
comparison of every frame with it (FORMATS.md, round 4)."""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest

from snail_bench.track import Feed, compare, opencv_converged, track_report
from snail_client.localize import Options
from snail_common.loc.problem import PoseVectors
from snail_common.loc.reference import reprojection_rms
from snail_common.loc.trust import pose_error
from snail_sim.sequences import handheld, turbo

FIELDS = {"points", "frames", "sequence", "fps", "latency_s", "runs_per_frame", "lost",
          "rms_ratio", "within", "pose_error", "link_bound_fps", "dropped", "setting",
          "client_cpu_s_per_frame", "scheme", "engine"}


@pytest.mark.parametrize("make", [handheld, turbo])
def test_the_sequences_move_like_a_camera_at_30_frames_per_second(make):
    seq = make(np.random.default_rng(2), 16, 90)
    assert len(seq.problems) == 90 and seq.fps == 30
    assert seq.problems[0].initial_pose is not None
    assert all(p.initial_pose is None for p in seq.problems[1:] if p is not None)
    moves = [pose_error(a.reference_pose.rvec, a.reference_pose.tvec, b.reference_pose)
             for a, b in zip(seq.problems[1:], seq.problems[:-1])]
    assert max(m["rotation_deg"] for m in moves) < 3.0
    assert max(m["translation"] for m in moves) < 0.05  # metres a frame
    for problem, ids in zip(seq.problems, seq.ids):
        assert problem.n <= 16 and np.array_equal(problem.points3d, seq.world[ids])
        err = problem.points2d - _project(problem, problem.reference_pose)
        assert np.sqrt(np.mean(err ** 2)) < 2.0  # pixel noise, not wrong matches


def _project(problem, pose):
    import cv2

    pix, _ = cv2.projectPoints(problem.points3d, pose.rvec, pose.tvec, problem.K,
                               problem.dist)
    return pix.reshape(-1, 2)


def test_turbo_fills_a_circuit_with_whole_tags_then_a_diagonal():
    """Six points are a tag's four corners and two opposite corners of the next largest
    (one tag alone leaves the pose undetermined to degrees); sixteen, four whole tags."""
    for points, tags in ((6, 2), (16, 4)):
        seq = turbo(np.random.default_rng(2), points, 30)
        for ids in seq.ids:
            assert len(ids) == points
            by_tag = {int(i) // 4: [] for i in ids}
            for i in ids:
                by_tag[int(i) // 4].append(int(i) % 4)
            corners = sorted(sorted(c) for c in by_tag.values())
            assert len(by_tag) == tags
            if points == 6:
                assert corners == [[0, 1, 2, 3], [0, 2]]


def test_opencv_converged_is_the_least_squares_minimum():
    seq = handheld(np.random.default_rng(3), 6, 2)
    problem = seq.problems[0]
    cv = opencv_converged(problem, problem.initial_pose)
    best = reprojection_rms(problem, cv.rvec, cv.tvec)
    rng = np.random.default_rng(0)
    for _ in range(20):  # any nudge of the pose fits worse
        nudged = PoseVectors(cv.rvec + rng.normal(scale=1e-4, size=3),
                             cv.tvec + rng.normal(scale=1e-4, size=3))
        assert reprojection_rms(problem, nudged.rvec, nudged.tvec) > best
    row = compare(problem, cv, cv)
    assert row["rms_ratio"] == 1.0 and row["within"] and row["deg"] == 0.0


def test_a_camera_feed_drops_what_a_slow_tracker_cannot_take():
    seq = handheld(np.random.default_rng(4), 6, 40)
    feed = Feed(seq, fps=200.0)
    taken = []
    for item in feed.items():
        taken.append(int(item.name))
        if len(taken) > 1:
            time.sleep(0.012)  # slower than the 5 ms between frames
    assert taken[0] == 0 and feed.dropped > 0
    assert len(taken) + feed.dropped == 40
    assert all(b > a for a, b in itertools.pairwise(taken))  # the newest, in order
    fast = Feed(seq, fps=None)
    assert [int(i.name) for i in fast.items()] == list(range(40)) and fast.dropped == 0


def test_the_report_has_the_formats_fields_and_measures_every_frame():
    options = Options(backend="float64", runs_per_frame=2)
    report = track_report((6,), 30, "handheld", options)["track"]
    entry = report["nx-sil-n6"]
    assert set(entry) >= FIELDS
    assert entry["frames"] == 30 and entry["points"] == 6 and entry["dropped"] == 0
    assert entry["setting"] == "offload" and entry["runs_per_frame"] == 2
    assert len(entry["per_frame"]) == 30
    assert entry["rms_ratio"]["median"] >= 1 - 1e-9  # OpenCV's is the minimum
    assert 0.0 <= entry["within"] <= 1.0
    assert entry["pose_error"]["deg_max"] >= 0 and entry["link_bound_fps"] is None
    truth = entry["truth_deg"]
    assert 0 <= truth["tracked"]["median"] <= truth["tracked"]["max"]
    assert 0 <= truth["opencv"]["median"] <= truth["opencv"]["max"] < 2.0
    ratios = [r["rms_ratio"] for r in entry["per_frame"]]
    assert entry["rms_ratio"]["max"] == pytest.approx(max(ratios), abs=1e-6)
