"""Problem files and sequences: valid files load, every bad input names its field."""

import copy
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shared_paths import EXAMPLES

from snail_common.loc.geometry import so3_exp
from snail_common.loc.problem import (
    ProblemError,
    check_in_front,
    load_problem,
    load_sequence,
    parse_problem,
    problem_to_json,
)

EXAMPLE_FILES = sorted(EXAMPLES.glob("*.json"))
BASE = json.loads((EXAMPLES / "synthetic_n6.json").read_text())


def _mutated(change) -> dict:
    obj = copy.deepcopy(BASE)
    change(obj)
    return obj


def _set(path: list, value):
    def change(obj):
        node = obj
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
    return change


def _delete(key: str):
    return lambda obj: obj.pop(key)


def _truncate(n: int):
    def change(obj):
        obj["points2d"] = obj["points2d"][:n]
        obj["points3d"] = obj["points3d"][:n]
    return change


BAD = [
    (_truncate(3), "points2d: need at least 4 points, got 3"),
    (_set(["points3d", 4, 2], math.nan), "points3d[4][2]: not a finite number"),
    (_set(["points2d", 0, 1], math.inf), "points2d[0][1]: not a finite number"),
    (_set(["points2d", 0, 1], "3"), "points2d[0][1]: not a number"),
    (_set(["points3d", 1, 0], True), "points3d[1][0]: not a number"),
    (_set(["points2d", 1], [1.0, 2.0, 3.0]), "points2d[1]: expected 2 numbers, got 3"),
    (_set(["points3d", 2], 5.0), "points3d[2]: expected 3 numbers, got float"),
    (_set(["points3d"], {"x": 1}), "points3d: expected a list of points"),
    (lambda o: o["points3d"].append([0.0, 0.0, 1.0]), "points2d: 6 points but points3d has 7"),
    (_set(["initial_pose", "rvec"], [0.1, 0.2]), "initial_pose.rvec: expected 3 numbers"),
    (lambda o: o["initial_pose"].pop("tvec"), "initial_pose.tvec: missing"),
    (_delete("initial_pose"), "initial_pose: missing"),
    (_set(["reference_pose", "tvec", 2], math.nan), "reference_pose.tvec[2]: not a finite"),
    (_set(["camera", "fx"], -800.0), "camera.fx: must be positive"),
    (lambda o: o["camera"].pop("cy"), "camera.cy: missing"),
    (_set(["camera", "dist"], [0.1, 0.0, 0.0]), "camera.dist: expected 4, 5, 8"),
    (_set(["camera", "dist"], [0.1, 0.0, 0.0, math.nan]), "camera.dist[3]: not a finite"),
    (_set(["camera", "width"], 0), "camera.width: expected a positive integer"),
    (_set(["format"], "snail-problem/2"), "format: expected 'snail-problem/1'"),
    (_delete("camera"), "camera: missing"),
]


@pytest.mark.parametrize("path", EXAMPLE_FILES, ids=lambda p: p.name)
def test_examples_load_and_are_in_front(path):
    obj = json.loads(path.read_text())
    problem = load_problem(path)
    assert problem.n == len(obj["points3d"]) >= 4
    assert problem.points2d.shape == (problem.n, 2) and problem.points3d.shape == (problem.n, 3)
    assert problem.K[0, 0] == obj["camera"]["fx"] and problem.K[1, 2] == obj["camera"]["cy"]
    np.testing.assert_array_equal(problem.initial_pose.rvec, obj["initial_pose"]["rvec"])
    assert problem.image_size == (obj["camera"]["width"], obj["camera"]["height"])
    np.testing.assert_array_equal(problem.dist, np.zeros(5))
    check_in_front(problem)


@pytest.mark.parametrize(("change", "message"), BAD, ids=[m.split(":")[0] for _, m in BAD])
def test_bad_fields_are_named(change, message):
    with pytest.raises(ProblemError) as err:
        parse_problem(_mutated(change))
    assert str(err.value).startswith(message)


@settings(max_examples=40, deadline=None)
@given(st.sampled_from([("points2d", 2), ("points3d", 3)]), st.data(),
       st.sampled_from([math.nan, math.inf, -math.inf, None, "1.0", [1.0]]))
def test_any_bad_coordinate_is_named_exactly(field, data, bad):
    name, width = field
    i = data.draw(st.integers(0, len(BASE[name]) - 1))
    k = data.draw(st.integers(0, width - 1))
    with pytest.raises(ProblemError) as err:
        parse_problem(_mutated(_set([name, i, k], bad)))
    assert str(err.value).startswith(f"{name}[{i}][{k}]: not a ")


def test_file_with_nan_literal_and_broken_json(tmp_path):
    path = tmp_path / "p.json"
    path.write_text(json.dumps(_mutated(_set(["points3d", 4, 2], math.nan))))
    assert "NaN" in path.read_text()
    with pytest.raises(ProblemError, match=r"^points3d\[4\]\[2\]: not a finite number"):
        load_problem(path)
    path.write_text('{"format": "snail-problem/1",\n "camera": }')
    with pytest.raises(ProblemError, match=r"^invalid JSON at line 2"):
        load_problem(path)
    with pytest.raises(ProblemError, match="cannot read"):
        load_problem(tmp_path / "missing.json")


def test_points_behind_camera_are_named():
    problem = load_problem(EXAMPLES / "synthetic_n64.json")
    pts = problem.points3d.copy()
    R = so3_exp(problem.initial_pose.rvec)
    t = problem.initial_pose.tvec
    # Put points 2 and 5 one unit behind the camera (camera z = -1).
    for i in (2, 5):
        cam = R @ pts[i] + t
        cam[2] = -1.0
        pts[i] = R.T @ (cam - t)
    bad = type(problem)(**{**problem.__dict__, "points3d": pts})
    with pytest.raises(ProblemError, match=r"^points3d\[2\], points3d\[5\]: behind the camera"):
        check_in_front(bad)
    # Many offenders: the first five by index, then a count.
    far = type(problem)(**{**problem.__dict__, "points3d": pts - 100.0 * (R.T @ [0, 0, 1])})
    with pytest.raises(ProblemError, match=r"points3d\[4\] and 59 more: behind"):
        check_in_front(far)


@pytest.mark.parametrize("path", EXAMPLE_FILES, ids=lambda p: p.name)
def test_json_round_trip(path):
    problem = load_problem(path)
    again = parse_problem(json.loads(json.dumps(problem_to_json(problem))))
    for field in ("K", "dist", "points2d", "points3d"):
        np.testing.assert_array_equal(getattr(again, field), getattr(problem, field))
    np.testing.assert_array_equal(again.reference_pose.tvec, problem.reference_pose.tvec)
    assert again.image_size == problem.image_size


def _frame(i: int, with_pose: bool) -> dict:
    obj = copy.deepcopy(BASE)
    obj["points2d"][0][0] += i  # tell the frames apart
    if not with_pose:
        del obj["initial_pose"]
    return obj


def test_sequence_json_lines(tmp_path):
    path = tmp_path / "seq.jsonl"
    lines = [json.dumps(_frame(i, i == 0)) for i in range(3)]
    path.write_text(lines[0] + "\n\n" + lines[1] + "\n" + lines[2] + "\n")
    frames = load_sequence(path)
    assert [f.points2d[0, 0] - BASE["points2d"][0][0] for f in frames] == [0, 1, 2]
    assert frames[0].initial_pose is not None
    assert frames[1].initial_pose is None and frames[2].initial_pose is None
    path.write_text(lines[1] + "\n")
    with pytest.raises(ProblemError, match=r"^line 1: initial_pose: missing"):
        load_sequence(path)
    bad = _frame(5, False)
    bad["points3d"][1][1] = math.nan
    path.write_text(lines[0] + "\n\n" + json.dumps(bad) + "\n")
    with pytest.raises(ProblemError, match=r"^line 3: points3d\[1\]\[1\]: not a finite"):
        load_sequence(path)


def test_sequence_folder_in_name_order(tmp_path):
    for name, i in (("b.json", 1), ("a.json", 0), ("c.json", 2)):
        (tmp_path / name).write_text(json.dumps(_frame(i, i == 0)))
    (tmp_path / "notes.txt").write_text("not a frame")
    frames = load_sequence(tmp_path)
    assert [f.points2d[0, 0] - BASE["points2d"][0][0] for f in frames] == [0, 1, 2]
    (tmp_path / "b.json").write_text(json.dumps(_mutated(_truncate(2))))
    with pytest.raises(ProblemError, match=r"^b\.json: points2d: need at least 4 points, got 2"):
        load_sequence(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ProblemError, match="no problems"):
        load_sequence(empty)
