"""Turbo: the robot's camera pose convention, the controller, and a whole run (float64
backend: the loop, not the circuits, is under test here; the garbled path is in
test_api/test_inputs_apriltag) with its log, video and plot."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from snail_demo.cli import main as demo
from snail_demo.turbo import RobotPose, control, room
from snail_demo.turbo_run import TARGET, run_turbo


def test_the_camera_looks_where_the_robot_heads():
    robot = RobotPose(0.3, -0.2, math.radians(30))
    pose = robot.camera()
    R, _ = cv2.Rodrigues(pose.rvec)
    assert np.allclose(-R.T @ pose.tvec, [0.3, -0.2, 0.12])
    assert np.allclose(R[2], [math.cos(math.radians(30)), math.sin(math.radians(30)), 0])
    assert np.allclose(R[1], [0, 0, -1])  # image down is world down
    back = RobotPose.from_camera(pose.rvec, pose.tvec)
    assert back.x == pytest.approx(0.3) and back.heading == pytest.approx(math.radians(30))


def test_every_tag_faces_into_the_room():
    for tag in room().tags.values():
        R, _ = cv2.Rodrigues(tag.rvec)
        to_centre = np.array([1.0, 0.0, tag.tvec[2]]) - tag.tvec
        assert R[2, 2] == pytest.approx(0) and R[2, 1] == pytest.approx(1)  # upright
        assert R[:, 2] @ to_centre > 0.5 * np.linalg.norm(to_centre)  # z at the viewer


@pytest.mark.parametrize("seed", range(5))
def test_the_controller_reaches_targets_from_the_odometry_alone(seed):
    rng = np.random.default_rng(seed)
    robot = RobotPose(*rng.uniform([0.2, -0.6], [0.6, 0.6]), rng.uniform(-0.6, 0.6))
    for _ in range(100):
        distance, turn, reached = control(robot, TARGET)
        assert abs(distance) <= 0.1 + 1e-12 and abs(turn) <= math.radians(15) + 1e-12
        if reached:
            break
        robot = robot.moved(distance, turn)
    assert reached
    assert math.hypot(robot.x - TARGET.x, robot.y - TARGET.y) < 0.01


def test_a_run_reaches_the_target_and_writes_log_video_and_plot(tmp_path):
    final = run_turbo(tmp_path, "float64", 0.0, 0, 60, 3)
    assert final["reached"]
    assert final["position_error_m"] < 0.02 and final["rotation_error_deg"] < 2
    log = json.loads((tmp_path / "turbo.json").read_text())
    assert log["final"] == final
    steps = log["steps"]
    assert len(steps) == final["steps"] > 5
    for step in steps:
        assert {"t", "true", "estimate", "iterations", "invocations", "seconds", "bytes",
                "client_cpu_s"} <= step.keys()
        assert step["status"] == "converged" and step["position_error_m"] < 0.03
        assert len(step["true"]["rvec"]) == len(step["estimate"]["tvec"]) == 3
    video = cv2.VideoCapture(str(tmp_path / "turbo.mp4"))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == len(steps)
    ok, picture = video.read()
    assert ok and picture.shape[1] == 2 * picture.shape[0] + 160  # 640x480 + 480x480
    plot = cv2.imread(str(tmp_path / "trajectory.png"))
    assert plot is not None and plot.shape == (720, 720, 3)


def test_a_link_delay_needs_links():
    out = CliRunner().invoke(demo, ["turbo", "--out", "x", "--backend", "cleartext",
                                    "--link-delay-ms", "20"])
    assert out.exit_code == 2 and "--link-delay-ms: only with --backend garbled" in out.output
