"""Camera files and tag maps: every malformed field is one line on stderr naming the file
and the field, exit 2; good files round-trip."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from click.testing import CliRunner

from snail_client.cli import main as client
from snail_client.inputs.camera import load_camera, parse_camera
from snail_client.inputs.fields import InputError
from snail_client.inputs.tagmap import load_tagmap, parse_tagmap

CAMERA = {"format": "snail-camera/1", "width": 640, "height": 480, "fx": 338.6, "fy": 338.9,
          "cx": 336.5, "cy": 230.5, "dist": [0.1, -0.02, 0.0, 0.0, 0.0]}
TAGMAP = {"format": "snail-tagmap/1", "family": "tag36h11",
          "tags": [{"id": 85, "size": 0.065, "rvec": [0, 0, 0], "tvec": [0, 0, 0]},
                   {"id": 3, "size": 0.1, "rvec": [0.1, 0, 0], "tvec": [0.2, 0, 0]}]}


def _set(obj, path, value):
    *parents, last = path
    for key in parents:
        obj = obj[key]
    if value is KeyError:
        del obj[last]
    else:
        obj[last] = value


BAD_CAMERAS = [
    (("format",), "snail-problem/1", "format"),
    (("fx",), KeyError, "fx: missing"),
    (("fy",), -3.0, "fy: must be positive"),
    (("cx",), "320", "cx: not a number"),
    (("dist",), [0.1, 0.2, 0.3], "dist: expected 4, 5, 8, 12, 14 numbers"),
    (("dist", 1), None, "dist[1]: not a number"),
    (("width",), 0, "width: expected a positive integer, got 0"),
    (("height",), KeyError, "height: missing"),
]

BAD_TAGMAPS = [
    (("format",), "snail-camera/1", "format"),
    (("family",), "tag25h9", "family: expected one of ['tag36h11']"),
    (("tags",), [], "tags: expected a non-empty list"),
    (("tags", 0), 7, "tags[0]: expected an object"),
    (("tags", 1, "id"), 85, "tags[1].id: tag 85 appears twice"),
    (("tags", 1, "id"), 587, "tags[1].id: 587 is not a tag36h11 id"),
    (("tags", 0, "id"), -1, "tags[0].id: expected an integer >= 0"),
    (("tags", 1, "size"), 0, "tags[1].size: must be positive"),
    (("tags", 0, "rvec"), [0, 0], "tags[0].rvec: expected 3 numbers, got 2"),
    (("tags", 1, "tvec"), KeyError, "tags[1].tvec: missing"),
    (("tags", 1, "tvec", 2), float("nan"), "tags[1].tvec[2]: not a finite number"),
]


def test_good_files_round_trip(tmp_path):
    camera = parse_camera(CAMERA)
    assert camera.size == (640, 480) and camera.K[0, 0] == 338.6 and camera.K[1, 2] == 230.5
    again = parse_camera(json.loads(json.dumps(camera.to_json())))
    assert again.size == camera.size and np.array_equal(again.K, camera.K)
    assert np.array_equal(again.dist, camera.dist)
    tagmap = parse_tagmap(TAGMAP)
    assert sorted(tagmap.tags) == [3, 85]
    corners = tagmap.tags[85].corners_world()
    assert np.allclose(corners, [[-0.0325, 0.0325, 0], [0.0325, 0.0325, 0],
                                 [0.0325, -0.0325, 0], [-0.0325, -0.0325, 0]])
    moved = tagmap.tags[3].corners_world()
    assert np.allclose(moved.mean(axis=0), [0.2, 0, 0])
    assert np.allclose(np.linalg.norm(moved[0] - moved[1]), 0.1)
    again = parse_tagmap(json.loads(json.dumps(tagmap.to_json())))
    assert np.array_equal(again.tags[3].corners_world(), moved)


def test_a_camera_without_size_or_distortion_is_fine():
    camera = parse_camera({k: v for k, v in CAMERA.items()
                           if k not in ("width", "height", "dist")})
    assert camera.size is None and not camera.dist.any()


@pytest.mark.parametrize(("path", "value", "message"), BAD_CAMERAS)
def test_a_bad_camera_field_is_named(tmp_path, path, value, message):
    bad = copy.deepcopy(CAMERA)
    _set(bad, path, value)
    file = tmp_path / "cam.json"
    file.write_text(json.dumps(bad))
    with pytest.raises(InputError) as err:
        load_camera(file)
    assert str(err.value).startswith(f"{file}: ") and message in str(err.value)


@pytest.mark.parametrize(("path", "value", "message"), BAD_TAGMAPS)
def test_a_bad_tag_map_field_is_named(tmp_path, path, value, message):
    bad = copy.deepcopy(TAGMAP)
    _set(bad, path, value)
    file = tmp_path / "map.json"
    file.write_text(json.dumps(bad))
    with pytest.raises(InputError) as err:
        load_tagmap(file)
    assert str(err.value).startswith(f"{file}: ") and message in str(err.value)


def test_files_that_are_not_json_are_named(tmp_path):
    file = tmp_path / "map.json"
    file.write_text('{"format": ')
    with pytest.raises(InputError, match=r"map\.json: invalid JSON at line 1"):
        load_tagmap(file)
    with pytest.raises(InputError, match=r"nothing\.json: cannot read"):
        load_camera(tmp_path / "nothing.json")


@pytest.mark.parametrize("which", ["camera", "tag map"])
def test_the_command_line_says_it_in_one_line_with_exit_2(tmp_path, which):
    cam, tags = copy.deepcopy(CAMERA), copy.deepcopy(TAGMAP)
    if which == "camera":
        cam["fx"] = 0
    else:
        tags["tags"][0]["size"] = "big"
    (tmp_path / "cam.json").write_text(json.dumps(cam))
    (tmp_path / "map.json").write_text(json.dumps(tags))
    (tmp_path / "img.png").write_bytes(b"")
    out = CliRunner().invoke(client, ["localize", "--image", str(tmp_path / "img.png"),
                                      "--tag-map", str(tmp_path / "map.json"),
                                      "--camera", str(tmp_path / "cam.json")])
    assert out.exit_code == 2, out.output
    assert out.stderr.count("\n") == 1 and "Traceback" not in out.output
    expected = "cam.json: fx: must be positive" if which == "camera" else (
        "map.json: tags[0].size: not a number")
    assert expected in out.stderr


@pytest.mark.parametrize(("args", "message"), [
    (["--image", "IMG"], "--image needs --tag-map and --camera"),
    (["--image", "IMG", "--input", "IMG"], "exactly one of --input, --image"),
    ([], "exactly one of --input, --image"),
    (["--input", "IMG", "--camera", "IMG"], "--camera: only with --image or --image-dir"),
])
def test_flags_that_do_not_go_together_are_usage_errors(tmp_path, args, message):
    image = tmp_path / "img.png"
    image.write_bytes(b"")
    args = [str(image) if a == "IMG" else a for a in args]
    out = CliRunner().invoke(client, ["localize", *args])
    assert out.exit_code == 2 and message in out.output, out.output
