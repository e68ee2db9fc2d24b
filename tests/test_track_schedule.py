"""The tracking schedule as a state machine, without servers: the first frame padded, then
exactly K runs from the prediction; lost, re-localized within the frames' own runs or
revealed; frames in flight planned from the state D frames back."""

from __future__ import annotations

import numpy as np
import pytest

from snail_common.loc.geometry import so3_exp
from snail_common.loc.problem import PoseVectors
from snail_common.loc.schedule import (
    INITIALIZING,
    LOST,
    RELOCALIZED,
    TRACKING,
    Outcome,
    Schedule,
    compose,
    relative,
)

A = PoseVectors(np.array([0.1, -0.2, 0.05]), np.array([0.3, 0.1, 2.0]))
STEP = PoseVectors(np.array([0.0, 0.01, 0.0]), np.array([0.02, 0.0, 0.0]))
CIRCUIT = "loc/nx-sil-n6"


def _same(a: PoseVectors, b: PoseVectors) -> bool:
    return bool(np.allclose(so3_exp(a.rvec), so3_exp(b.rvec), atol=1e-12)
                and np.allclose(a.tvec, b.tvec, atol=1e-12))


def _trusted(pose: PoseVectors, runs: int = 1) -> Outcome:
    return Outcome(True, pose, runs, CIRCUIT)


def test_compose_and_relative_undo_each_other():
    B = compose(STEP, A)
    assert _same(compose(relative(A, B), A), B)
    assert _same(relative(A, A), PoseVectors(np.zeros(3), np.zeros(3)))
    # the motion acts on the camera: the camera centre moves by -R_new^T tm
    assert not _same(B, A)


def test_the_first_frame_is_padded_and_later_ones_get_exactly_k_runs():
    schedule = Schedule(runs_per_frame=2, min_invocations=20)
    first = schedule.plan(0)
    assert (first.padded, first.runs, first.start) == (True, 20, None)
    assert schedule.waits_for_answers and schedule.state == INITIALIZING
    seen = schedule.observe(first, _trusted(A, runs=20))
    assert (seen.track_status, seen.revealed) == (TRACKING, False)
    for index in range(1, 5):
        plan = schedule.plan(index)
        assert (plan.padded, plan.runs, plan.revealed) == (False, 2, False)
        assert _same(plan.start, A)  # no motion known, no model: the last trusted pose
        schedule.observe(plan, _trusted(A, runs=2))
    assert schedule.state == TRACKING and not schedule.waits_for_answers


def test_the_warm_up_frames_get_two_runs_whatever_the_answers():
    """Fixed in advance: frames 1 .. W get two runs (one was asked for) trusted or not."""
    schedule = Schedule(runs_per_frame=1, min_invocations=20, warmup=2)
    schedule.observe(schedule.plan(0), _trusted(A, runs=20))
    runs = []
    for index in range(1, 6):
        plan = schedule.plan(index)
        runs.append(plan.runs)
        schedule.observe(plan, Outcome(index != 1, A, plan.runs, CIRCUIT))  # 1 is lost
    assert runs == [2, 2, 1, 1, 1]
    more = Schedule(runs_per_frame=3, warmup=2)  # K above two stays K
    more.observe(more.plan(0), _trusted(A, runs=20))
    assert more.plan(1).runs == 3


def test_a_padded_first_frame_that_needed_more_runs_is_revealed():
    schedule = Schedule(runs_per_frame=1, min_invocations=20)
    seen = schedule.observe(schedule.plan(0), _trusted(A, runs=21))
    assert seen.revealed


def test_odometry_and_constant_velocity_move_the_prediction():
    schedule = Schedule(runs_per_frame=1, min_invocations=20)
    schedule.observe(schedule.plan(0), _trusted(A, runs=20))
    plan = schedule.plan(1, motion=STEP)
    assert _same(plan.start, compose(STEP, A))
    model = Schedule(runs_per_frame=1, motion_model="constant-velocity")
    model.observe(model.plan(0), _trusted(A, runs=20))
    B = compose(STEP, A)
    model.observe(model.plan(1), _trusted(B))
    assert _same(model.plan(2).start, compose(STEP, B))  # the last frames' motion again


def _followed(schedule: Schedule, poses: list[PoseVectors]) -> list[PoseVectors]:
    """Each frame's planned start, every answer trusted and equal to ``poses``."""
    starts = []
    for index, pose in enumerate(poses):
        plan = schedule.plan(index)
        starts.append(plan.start)
        schedule.observe(plan, _trusted(pose, runs=20 if index == 0 else 1))
    return starts


def test_auto_extrapolates_a_steady_motion_once_it_has_predicted_better():
    """A camera moving by STEP every frame: the last pose is one STEP behind each answer,
    constant velocity on it exactly; after a few trusted frames auto moves the
    prediction and then starts on the answer."""
    poses = [A]
    for _ in range(8):
        poses.append(compose(STEP, poses[-1]))
    schedule = Schedule(runs_per_frame=1)
    starts = _followed(schedule, poses)
    assert _same(starts[2], poses[1])  # no vote yet: the last trusted pose
    assert all(_same(start, pose) for start, pose in zip(starts[4:], poses[4:]))
    assert schedule.plan(len(poses)).prediction == "constant-velocity"
    assert schedule.plan(len(poses), motion=STEP).prediction == "odometry"
    assert Schedule().plan(0).prediction is None  # the padded first frame: its own start


def test_auto_keeps_the_last_pose_when_the_motion_jitters():
    """A camera shaking back and forth about A: the last frames' motion points the wrong
    way every time, so auto never extrapolates it (constant-velocity does)."""
    poses = [A if i % 2 == 0 else compose(STEP, A) for i in range(10)]
    schedule = Schedule(runs_per_frame=1)
    auto = _followed(schedule, poses)
    assert all(_same(start, pose) for start, pose in zip(auto[1:], poses[:-1]))
    assert schedule.plan(len(poses)).prediction == "last-pose"
    forced = _followed(Schedule(runs_per_frame=1, motion_model="constant-velocity"), poses)
    assert not _same(forced[3], poses[2])
    assert _same(forced[3], compose(relative(poses[1], poses[2]), poses[2]))


def test_lost_answers_that_improved_carry_the_motion_on():
    """The map-owner device with one run a frame judges only the prediction's fit: its
    first tracked frames, predicted before any motion is known, come out lost though
    their answers are right. Those answers still give the motion, so the prediction soon
    moves with the camera and the track is trusted again."""
    poses = [A]
    for _ in range(6):
        poses.append(compose(STEP, poses[-1]))
    schedule = Schedule(runs_per_frame=1)
    schedule.observe(schedule.plan(0), _trusted(poses[0], runs=20))
    for index in (1, 2):
        schedule.observe(schedule.plan(index),
                         Outcome(False, poses[index], 1, CIRCUIT, improved=True))
    plan = schedule.plan(3)
    assert _same(plan.start, poses[3])  # moved by the motion of the lost answers
    assert schedule.observe(plan, _trusted(poses[3])).track_status == RELOCALIZED
    schedule.observe(schedule.plan(4), Outcome(False, poses[0], 1, CIRCUIT, improved=False))
    assert _same(schedule.plan(5).start, poses[3])  # it went nowhere: no motion to trust


def test_a_lost_frame_keeps_its_k_runs_and_restarts_from_its_answer_if_it_improved():
    schedule = Schedule(runs_per_frame=1, min_invocations=20)
    schedule.observe(schedule.plan(0), _trusted(A, runs=20))
    wrong = compose(STEP, compose(STEP, A))
    seen = schedule.observe(schedule.plan(1), Outcome(False, wrong, 1, CIRCUIT, improved=True))
    assert (seen.track_status, seen.revealed, schedule.state) == (LOST, False, LOST)
    plan = schedule.plan(2)
    assert (plan.padded, plan.runs) == (False, 1)  # the servers see nothing change
    assert _same(plan.start, wrong)  # a re-localization spread over the frames' own runs
    seen = schedule.observe(plan, Outcome(False, A, 1, CIRCUIT, improved=False))
    assert _same(schedule.plan(3).start, A)  # it went nowhere: the last trusted pose
    seen = schedule.observe(schedule.plan(4), _trusted(A))
    assert seen.track_status == RELOCALIZED and schedule.state == TRACKING


def test_reveal_gives_a_lost_track_a_padded_frame_and_says_so():
    schedule = Schedule(runs_per_frame=1, min_invocations=20, on_lost="reveal")
    schedule.observe(schedule.plan(0), _trusted(A, runs=20))
    schedule.observe(schedule.plan(1), Outcome(False, None, 1, CIRCUIT))
    plan = schedule.plan(2)
    assert (plan.padded, plan.runs, plan.revealed) == (True, 20, True)
    assert schedule.observe(plan, _trusted(A, runs=20)).revealed


def test_another_circuit_or_count_than_the_schedules_is_revealed():
    schedule = Schedule(runs_per_frame=1, min_invocations=20)
    schedule.observe(schedule.plan(0), _trusted(A, runs=20))
    assert schedule.observe(schedule.plan(1), Outcome(True, A, 1, "loc/nx-sil-n12")).revealed
    assert schedule.observe(schedule.plan(2), Outcome(True, A, 2, CIRCUIT)).revealed
    assert not schedule.observe(schedule.plan(3), _trusted(A)).revealed


def test_frames_in_flight_are_planned_from_the_state_d_frames_back():
    """With two in flight, frame t starts from frame t-2's answer moved over the motions
    since, even when frame t-1's answer is in already (timing must not count)."""
    schedule = Schedule(runs_per_frame=1, min_invocations=20)
    schedule.observe(schedule.plan(0), _trusted(A, runs=20))
    p1 = schedule.plan(1, motion=STEP, lag=2)
    p2 = schedule.plan(2, motion=STEP, lag=2)
    assert _same(p1.start, compose(STEP, A)) and _same(p2.start, compose(STEP, p1.start))
    B = compose(STEP, compose(STEP, A))
    schedule.observe(p1, _trusted(B))
    schedule.observe(p2, _trusted(A))
    p3 = schedule.plan(3, lag=2)
    assert _same(p3.start, compose(STEP, B))  # frame 1's answer and frame 2's motion
    assert _same(schedule.plan(4, lag=1).start, A)


def test_zero_runs_per_frame_pads_every_frame_as_before():
    schedule = Schedule(runs_per_frame=0, min_invocations=20)
    schedule.observe(schedule.plan(0), _trusted(A, runs=20))
    plan = schedule.plan(1)
    assert (plan.padded, plan.runs, plan.revealed) == (True, 20, False)
    assert _same(plan.start, A)


@pytest.mark.parametrize(("kw", "flag"), [({"runs_per_frame": -1}, "--runs-per-frame"),
                                          ({"on_lost": "panic"}, "--on-lost"),
                                          ({"motion_model": "magic"}, "--motion-model")])
def test_bad_settings_are_named(kw, flag):
    with pytest.raises(ValueError, match=flag):
        Schedule(**kw)
