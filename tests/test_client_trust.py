"""Whether a pose can be trusted: status, exit codes and the reason on stderr; degenerate
inputs named before any circuit runs; track goes on past a bad frame and keeps what it
computed; error against a reference pose."""

from __future__ import annotations

import json

import numpy as np
from click.testing import CliRunner
from shared_paths import EXAMPLES

from snail_client.cli import main
from snail_common.loc.geometry import rvec_from_matrix, so3_exp
from snail_common.loc.problem import PoseVectors, load_problem
from snail_common.loc.trust import assess, degenerate, pose_error

BASE = json.loads((EXAMPLES / "synthetic_n6.json").read_text())


def _write(tmp_path, name: str, obj) -> str:
    path = tmp_path / name
    path.write_text(json.dumps(obj, indent=1))
    return str(path)


def _localize(*args: str):
    return CliRunner().invoke(main, ["localize", "--backend", "float64", "--json", *args])


def test_a_good_fit_is_converged_exit_0_with_its_error_against_the_reference(tmp_path):
    out = _localize("--input", str(EXAMPLES / "synthetic_n6.json"))
    assert out.exit_code == 0, out.output
    record = json.loads(out.stdout)
    assert record["status"] == "converged" and record["converged"] is True
    assert record["warnings"] == []
    assert record["error"]["rotation_deg"] < 0.5 and record["error"]["translation"] < 0.05


def test_a_bad_fit_is_not_trusted_exit_3(tmp_path):
    bad = dict(BASE, points2d=(np.array(BASE["points2d"])
                               + np.random.default_rng(0).normal(0, 60, (6, 2))).tolist())
    out = _localize("--input", _write(tmp_path, "bad.json", bad))
    assert out.exit_code == 3
    record = json.loads(out.stdout)
    assert record["status"] == "bad_fit" and record["converged"] is False
    assert "pose not trusted (bad_fit)" in out.stderr and "--max-rms-px 8" in out.stderr
    loose = _localize("--input", _write(tmp_path, "bad.json", bad), "--max-rms-px", "1000")
    assert loose.exit_code == 0 and json.loads(loose.stdout)["status"] == "converged"


def test_the_iteration_limit_is_not_convergence(tmp_path):
    out = _localize("--input", str(EXAMPLES / "synthetic_n6.json"), "--max-iterations", "1")
    assert out.exit_code == 3
    assert json.loads(out.stdout)["status"] == "not_converged"


def test_degenerate_points_are_named_before_any_run(tmp_path):
    pts = np.array(BASE["points3d"])
    line = pts[0] + np.outer(np.linspace(0, 1, 6), pts[1] - pts[0])
    out = CliRunner().invoke(main, ["localize", "--json", "--input",
                                    _write(tmp_path, "line.json",
                                           dict(BASE, points3d=line.tolist()))])
    assert out.exit_code == 3, out.output
    record = json.loads(out.stdout)
    assert record["status"] == "degenerate" and "one line" in out.stderr
    assert record["invocations"] == 0  # the garbled backend never ran a circuit
    few = dict(BASE, points2d=BASE["points2d"][:3], points3d=BASE["points3d"][:3])
    out = CliRunner().invoke(main, ["localize", "--input", _write(tmp_path, "few.json", few)])
    assert out.exit_code == 2 and "at least 4 points" in out.stderr  # refused as input


def test_image_points_on_a_line_mean_a_plane_through_the_camera():
    problem = load_problem(EXAMPLES / "synthetic_n6.json")
    problem.points2d[:, 1] = 2 * problem.points2d[:, 0] + 3
    assert "plane through the camera centre" in degenerate(problem)


def test_points_behind_the_camera_outrank_everything():
    problem = load_problem(EXAMPLES / "synthetic_n6.json")
    ref = problem.reference_pose
    turn = so3_exp(np.array([0.0, np.pi, 0.0]))  # the camera turned around: z -> -z
    status, warnings = assess(problem, rvec_from_matrix(turn @ so3_exp(ref.rvec)),
                              turn @ ref.tvec, True, 0.1)
    assert status == "behind_camera" and "behind the camera" in warnings[0]
    status, _ = assess(problem, ref.rvec, ref.tvec, True, 0.1)
    assert status == "converged"


def test_points_outside_the_image_are_a_warning():
    problem = load_problem(EXAMPLES / "synthetic_n6.json")
    ref = problem.reference_pose
    small = type(problem)(**{**problem.__dict__, "image_size": (10, 10)})
    status, warnings = assess(small, ref.rvec, ref.tvec, True, 0.1)
    assert status == "converged" and "outside the 10x10 image" in warnings[0]


def test_pose_error_measures_rotation_in_degrees_and_camera_position():
    ref = PoseVectors(np.array([0.1, 0.2, 0.3]), np.array([0.5, -0.2, 4.0]))
    assert pose_error(ref.rvec, ref.tvec, ref) == {"rotation_deg": 0.0, "translation": 0.0}
    turned = so3_exp(np.array([0.0, 0.0, np.radians(2.0)])) @ so3_exp(ref.rvec)
    err = pose_error(rvec_from_matrix(turned), ref.tvec, ref)
    assert abs(err["rotation_deg"] - 2.0) < 1e-9


def test_track_names_a_bad_frame_goes_on_and_keeps_its_output(tmp_path):
    frames = [BASE, dict(BASE, points2d=BASE["points2d"][:2]), BASE]
    seq = _write(tmp_path, "seq.json", frames)  # a JSON array of problems
    out_file = tmp_path / "out.json"
    out = CliRunner().invoke(main, ["track", "--backend", "float64", "--input", seq,
                                    "--output", str(out_file)])
    assert out.exit_code == 3
    assert "frame 1 ([1])" in out.stderr
    written = json.loads(out_file.read_text())
    # the first frame padded and converged, the third one run tracked from its pose
    assert [r.get("status") for r in written] == ["converged", None, "tracked"]
    assert [r["track_status"] for r in written] == ["tracking", "lost", "relocalized"]
    assert "failure" in written[1] and "points2d" in written[1]["failure"]
    fast = CliRunner().invoke(main, ["track", "--backend", "float64", "--input", seq,
                                     "--output", str(out_file), "--fail-fast"])
    assert fast.exit_code == 3 and len(json.loads(out_file.read_text())) == 2


def test_track_reads_one_pretty_printed_problem(tmp_path):
    out = CliRunner().invoke(main, ["track", "--backend", "float64", "--json", "--input",
                                    _write(tmp_path, "one.json", BASE)])
    assert out.exit_code == 0, out.output
    assert json.loads(out.stdout.splitlines()[0])["status"] == "converged"
