"""snail-map/1 and snail-frame/1 files: what they hold, and a named error for each kind
of bad field (exit 2 at the command line, never a traceback)."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from shared_paths import EXAMPLES

from snail_common.loc import mapfile
from snail_common.loc.mapfile import load_frame, load_map, parse_frame, parse_map
from snail_common.loc.problem import ProblemError, load_problem


def split_example(name: str = "synthetic_n12.json", extra: int = 50, seed: int = 0
                  ) -> tuple[dict, dict]:
    """A shared example as the two files of the map-owner setting: the map holds the
    example's 3D points under shuffled ids among ``extra`` other points."""
    obj = json.loads((EXAMPLES / name).read_text())
    rng = np.random.default_rng(seed)
    n = len(obj["points3d"])
    ids = rng.permutation(10 * (n + extra))[:n + extra]
    others = rng.normal(size=(extra, 3)).tolist()
    points = [{"id": int(i), "xyz": p} for i, p in zip(ids, obj["points3d"] + others)]
    order = rng.permutation(len(points))
    map_obj = {"format": "snail-map/1", "points": [points[i] for i in order]}
    frame = {"format": "snail-frame/1", "camera": obj["camera"], "points2d": obj["points2d"],
             "map_ids": [int(i) for i in ids[:n]], "initial_pose": obj["initial_pose"]}
    return map_obj, frame


def test_a_frame_and_its_map_make_the_original_problem(tmp_path):
    map_obj, frame_obj = split_example()
    (tmp_path / "map.json").write_text(json.dumps(map_obj))
    (tmp_path / "frame.json").write_text(json.dumps(frame_obj))
    points, frame = load_map(tmp_path / "map.json"), load_frame(tmp_path / "frame.json")
    original = load_problem(EXAMPLES / "synthetic_n12.json")
    assert len(points.ids) == 62 and frame.n == 12
    problem = frame.problem(points)
    assert np.array_equal(problem.points3d, original.points3d)
    assert np.array_equal(problem.points2d, original.points2d)
    assert np.array_equal(problem.K, original.K)
    assert np.array_equal(problem.initial_pose.tvec, original.initial_pose.tvec)
    assert problem.image_size == original.image_size


def test_select_names_the_first_id_not_in_the_map():
    map_obj, frame_obj = split_example()
    points = parse_map(map_obj)
    frame_obj["map_ids"][3] = 10**6 + 1
    frame_obj["map_ids"][7] = 10**6 + 2
    with pytest.raises(ProblemError, match=r"^map_ids\[3\]: map point 1000001 is not in"):
        parse_frame(frame_obj).problem(points)


def bad_map(path: str, value) -> dict:
    obj, _ = split_example()
    obj = copy.deepcopy(obj)
    *parents, last = path
    target = obj
    for key in parents:
        target = target[key]
    if value is KeyError:
        del target[last]
    else:
        target[last] = value
    return obj


@pytest.mark.parametrize(("path", "value", "message"), [
    (("format",), "snail-problem/1", r"^format: expected 'snail-map/1'"),
    (("points",), KeyError, r"^points: missing"),
    (("points",), {"id": 1}, r"^points: expected a list, got dict"),
    (("points",), [], r"^points: expected 1 to 1000000 entries, got 0"),
    (("points", 4), [1, 2, 3], r"^points\[4\]: expected an object"),
    (("points", 4, "id"), KeyError, r"^points\[4\]\.id: missing"),
    (("points", 4, "id"), True, r"^points\[4\]\.id: expected an integer id"),
    (("points", 4, "id"), -1, r"^points\[4\]\.id: expected an integer id"),
    (("points", 4, "id"), 1 << 32, r"^points\[4\]\.id: expected an integer id"),
    (("points", 4, "id"), 3.0, r"^points\[4\]\.id: expected an integer id"),
    (("points", 4, "xyz"), [1, 2], r"^points\[4\]\.xyz: expected 3 numbers, got 2"),
    (("points", 4, "xyz"), [1, "2", 3], r"^points\[4\]\.xyz\[1\]: not a number"),
    (("points", 4, "xyz"), [1, float("inf"), 3], r"^points\[4\]\.xyz\[1\]: not a finite"),
])
def test_bad_map_fields_are_named(path, value, message):
    with pytest.raises(ProblemError, match=message):
        parse_map(bad_map(path, value))


def test_duplicate_ids_name_both_points():
    obj, _ = split_example()
    obj["points"][9]["id"] = obj["points"][2]["id"]
    with pytest.raises(ProblemError, match=r"^points\[9\]\.id: \d+ is also points\[2\]\.id"):
        parse_map(obj)


def test_the_map_size_is_bounded_before_per_point_work(monkeypatch):
    monkeypatch.setattr(mapfile, "MAX_MAP_POINTS", 10)
    obj = {"format": "snail-map/1", "points": [None] * 11}  # bad points: never looked at
    with pytest.raises(ProblemError, match=r"^points: expected 1 to 10 entries, got 11"):
        parse_map(obj)


def frame_with(key: str, value) -> dict:
    _, frame = split_example()
    if value is KeyError:
        del frame[key]
    else:
        frame[key] = value
    return frame


@pytest.mark.parametrize(("key", "value", "message"), [
    ("format", None, r"^format: expected 'snail-frame/1'"),
    ("camera", KeyError, r"^camera: missing"),
    ("camera", {"fx": 1, "fy": 1, "cx": 0}, r"^camera\.cy: missing"),
    ("camera", {"fx": -1, "fy": 1, "cx": 0, "cy": 0}, r"^camera\.fx: must be positive"),
    ("points2d", [[1, 2]] * 3, r"^points2d: expected 4 to 65536 entries, got 3"),
    ("points2d", [[1, 2]] * 11 + [[1]], r"^points2d\[11\]: expected 2 numbers"),
    ("map_ids", KeyError, r"^map_ids: missing"),
    ("map_ids", [1, 2], r"^map_ids: 2 ids but points2d has 12 points"),
    ("map_ids", [1] * 11 + ["7"], r"^map_ids\[11\]: expected an integer id"),
    ("map_ids", "1,2,3", r"^map_ids: expected a list, got str"),
    ("initial_pose", KeyError, r"^initial_pose: missing"),
    ("initial_pose", {"rvec": [0, 0, 0]}, r"^initial_pose\.tvec: missing"),
])
def test_bad_frame_fields_are_named(key, value, message):
    with pytest.raises(ProblemError, match=message):
        parse_frame(frame_with(key, value))


def test_a_frame_is_not_a_map_and_not_a_list():
    _, frame = split_example()
    with pytest.raises(ProblemError, match=r"^format: expected 'snail-map/1'"):
        parse_map(frame)
    with pytest.raises(ProblemError, match=r"^frame: expected an object, got list"):
        parse_frame([frame])


def test_files_too_large_unreadable_or_not_json(tmp_path, monkeypatch):
    path = tmp_path / "map.json"
    path.write_text(json.dumps(split_example()[0]))
    monkeypatch.setattr(mapfile, "MAX_FILE_BYTES", 100)
    with pytest.raises(ProblemError, match="more than the 100 read"):
        load_map(path)
    monkeypatch.undo()
    with pytest.raises(ProblemError, match="cannot read"):
        load_frame(tmp_path / "absent.json")
    path.write_text('{"format": "snail-map/1", "points": [')
    with pytest.raises(ProblemError, match="invalid JSON at line 1"):
        load_map(path)
