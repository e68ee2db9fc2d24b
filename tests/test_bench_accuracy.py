"""``snail-bench accuracy``: the client's loop on the circuits' mirror against OpenCV over
random scenes, planar ones included, with every failure listed and the exit status set by
the pass rate."""

from __future__ import annotations

import json

import numpy as np
from click.testing import CliRunner

from snail_bench import accuracy
from snail_bench.cli import main


def test_planar_scenes_lie_on_one_plane_and_others_do_not():
    planes = {}
    for k in range(40):
        n, planar, problem = accuracy.scene(3, k, planar_share=0.5)
        pts = problem.points3d - problem.points3d.mean(axis=0)
        flatness = np.linalg.svd(pts, compute_uv=False)[-1] / np.linalg.norm(pts)
        planes.setdefault(planar, []).append(flatness)
        assert accuracy.MIN_POINTS <= n <= accuracy.MAX_POINTS == 256
    assert max(planes[True]) < 1e-9 < min(planes[False])


def test_a_sweep_matches_opencv_and_reports_json():
    result = CliRunner().invoke(main, ["-q", "accuracy", "--scenes", "25", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)["accuracy"]
    for algorithm in ("lm", "gn"):
        row = report[algorithm]
        assert (row["passed"], row["scenes"], row["failures"]) == (25, 25, [])
        assert row["not_converged"] == []
        # every circuit run is the start or a trial step: re-damping runs none
        assert row["invocations"]["max"] == row["iterations"]["max"] + 1
        kinds = row["passed_by_kind"]
        assert kinds["planar"]["scenes"] + kinds["general"]["scenes"] == 25


def test_a_scene_off_opencv_is_listed_and_fails_the_run(monkeypatch):
    real = accuracy.compare_with_opencv
    calls = []

    def one_bad(problem, rvec, tvec):
        check = real(problem, rvec, tvec)
        calls.append(1)
        return {**check, "ok": check["ok"] and len(calls) != 3}

    monkeypatch.setattr(accuracy, "compare_with_opencv", one_bad)
    result = CliRunner().invoke(main, ["-q", "accuracy", "--scenes", "10",
                                       "--algorithm", "lm"])
    assert result.exit_code == 1
    assert "lm: 9/10 within" in result.output and "scene 2: n=" in result.output
