"""COLMAP models: the text and binary readers agree on a model this test writes both ways
(its own writers, from COLMAP's documented formats), each supported camera model gives
back the model's pose (points projected with COLMAP's own equations and pixel convention),
--max-points keeps the best-observed points, and every malformed folder exits 2 naming the
file and the record or field at fault."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from click.testing import CliRunner

from snail_client.cli import main as client
from snail_client.inputs.colmap import MODEL_IDS, colmap_problem, read_model
from snail_client.inputs.fields import InputError
from snail_client.localize import Options, localize
from snail_common.loc.backends import Float64Backend
from snail_common.loc.geometry import so3_exp

PARAMS = {  # COLMAP parameter order of each model
    "SIMPLE_PINHOLE": [620.0, 320.0, 240.0],
    "PINHOLE": [610.0, 630.0, 318.0, 243.0],
    "SIMPLE_RADIAL": [620.0, 322.0, 238.0, -0.12],
    "RADIAL": [615.0, 321.0, 241.0, -0.2, 0.05],
    "OPENCV": [612.0, 618.0, 319.0, 242.0, -0.25, 0.07, 1e-3, -2e-3],
    "FULL_OPENCV": [612.0, 618.0, 319.0, 242.0, -0.25, 0.07, 1e-3, -2e-3, 0.01, 0.02,
                    -0.01, 0.005],
}


def colmap_project(model: str, params: list[float], cam: np.ndarray) -> np.ndarray:
    """COLMAP's projection (src/colmap/sensor/models.h) of camera-frame points, in its
    pixel convention (top-left pixel centre at (0.5, 0.5))."""
    x, y = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
    p = params
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy, k = p[1], p[2], p[3:]
    else:
        fx, fy, cx, cy, k = p[0], p[1], p[2], p[3], p[4:]
    r2 = x * x + y * y
    if model in ("SIMPLE_PINHOLE", "PINHOLE"):
        dx, dy = x, y
    elif model == "SIMPLE_RADIAL":
        dx, dy = x * (1 + k[0] * r2), y * (1 + k[0] * r2)
    elif model == "RADIAL":
        radial = 1 + k[0] * r2 + k[1] * r2 * r2
        dx, dy = x * radial, y * radial
    else:
        k1, k2, p1, p2 = k[:4]
        k3, k4, k5, k6 = k[4:] if model == "FULL_OPENCV" else (0, 0, 0, 0)
        radial = ((1 + k1 * r2 + k2 * r2**2 + k3 * r2**3)
                  / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3))
        dx = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack([fx * dx + cx, fy * dy + cy])


def quaternion(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix (w > 0 branch is enough for these poses)."""
    w = np.sqrt(1 + np.trace(R)) / 2
    return np.array([w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w),
                     (R[1, 0] - R[0, 1]) / (4 * w)])


def make_model(model: str, rng: np.random.Generator, n: int = 30) -> dict:
    """Two registered images of n points; image 1 sees all of them (plus 3 unmatched
    features), image 2 the first half, so those points have tracks of 2."""
    params = PARAMS[model]
    xyz = rng.uniform([-1, -1, 4], [1, 1, 6], size=(n, 3))
    images = []
    for image_id, (rvec, tvec, seen) in enumerate(
            [(np.array([0.1, -0.2, 0.05]), np.array([0.2, -0.1, 0.3]), n),
             (np.array([-0.1, 0.15, 0.0]), np.array([-0.3, 0.0, 0.1]), n // 2)], 1):
        R = so3_exp(rvec)
        uv = colmap_project(model, params, xyz[:seen] @ R.T + tvec)
        ids = np.arange(1, seen + 1)
        extra = rng.uniform([0, 0], [640, 480], size=(3, 2))
        images.append({"id": image_id, "q": quaternion(R), "t": tvec, "camera_id": 1,
                       "name": f"frame_{image_id:03d}.jpg", "xys": np.vstack([uv, extra]),
                       "ids": np.concatenate([ids, [-1, -1, -1]])})
    tracks = {i + 1: [(1, i)] + ([(2, i)] if i < n // 2 else []) for i in range(n)}
    errors = rng.uniform(0.1, 1.0, size=n)
    return {"camera": (1, model, 640, 480, params), "images": images,
            "points": [(i + 1, xyz[i], errors[i], tracks[i + 1]) for i in range(n)]}


def write_text(m: dict, folder) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    cam_id, model, w, h, params = m["camera"]
    (folder / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: 1\n"
        f"{cam_id} {model} {w} {h} {' '.join(repr(float(p)) for p in params)}\n")
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for im in m["images"]:
        pose = " ".join(repr(float(v)) for v in [*im["q"], *im["t"]])
        lines.append(f"{im['id']} {pose} {im['camera_id']} {im['name']}")
        lines.append(" ".join(f"{x!r} {y!r} {int(i)}" for (x, y), i in
                              zip(im["xys"].tolist(), im["ids"])))
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"]
    for pid, xyz, err, track in m["points"]:
        pairs = " ".join(f"{a} {b}" for a, b in track)
        lines.append(f"{pid} {' '.join(repr(float(v)) for v in xyz)} 128 128 128 "
                     f"{float(err)!r} {pairs}")
    (folder / "points3D.txt").write_text("\n".join(lines) + "\n")


def write_binary(m: dict, folder) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    cam_id, model, w, h, params = m["camera"]
    (folder / "cameras.bin").write_bytes(
        struct.pack("<Q", 1) + struct.pack("<iiQQ", cam_id, MODEL_IDS[model][0], w, h)
        + struct.pack(f"<{len(params)}d", *params))
    out = struct.pack("<Q", len(m["images"]))
    for im in m["images"]:
        out += struct.pack("<i7di", im["id"], *im["q"], *im["t"], im["camera_id"])
        out += im["name"].encode() + b"\0" + struct.pack("<Q", len(im["ids"]))
        for (x, y), i in zip(im["xys"], im["ids"]):
            out += struct.pack("<ddq", x, y, int(i))
    (folder / "images.bin").write_bytes(out)
    out = struct.pack("<Q", len(m["points"]))
    for pid, xyz, err, track in m["points"]:
        out += struct.pack("<Q3d3BdQ", pid, *xyz, 128, 128, 128, err, len(track))
        out += b"".join(struct.pack("<ii", a, b) for a, b in track)
    (folder / "points3D.bin").write_bytes(out)


@pytest.fixture(scope="module")
def opencv_model(tmp_path_factory):
    root = tmp_path_factory.mktemp("colmap")
    m = make_model("OPENCV", np.random.default_rng(1))
    write_text(m, root / "txt")
    write_binary(m, root / "bin")
    return root, m


def test_text_and_binary_readers_agree(opencv_model):
    root, m = opencv_model
    txt, binary = read_model(root / "txt"), read_model(root / "bin")
    assert (txt.kind, binary.kind) == ("txt", "bin")
    assert txt.cameras.keys() == binary.cameras.keys() == {1}
    a, b = txt.cameras[1], binary.cameras[1]
    assert (a.model, a.width, a.height) == (b.model, b.width, b.height) == ("OPENCV", 640, 480)
    assert np.array_equal(a.params, b.params) and a.params.tolist() == PARAMS["OPENCV"]
    assert txt.images.keys() == binary.images.keys() == {1, 2}
    for k, im in enumerate(m["images"], 1):
        x, y = txt.images[k], binary.images[k]
        assert x.name == y.name == im["name"] and x.camera_id == y.camera_id == 1
        assert np.array_equal(x.qvec, y.qvec) and np.array_equal(x.tvec, y.tvec)
        assert np.array_equal(x.xys, y.xys) and np.array_equal(x.xys, im["xys"])
        assert np.array_equal(x.point3d_ids, y.point3d_ids)
        assert x.point3d_ids.tolist() == im["ids"].tolist()
    assert txt.points.keys() == binary.points.keys() == set(range(1, 31))
    for pid in txt.points:
        p, q = txt.points[pid], binary.points[pid]
        assert np.array_equal(p.xyz, q.xyz) and p.error == q.error
        assert p.track_length == q.track_length == (2 if pid <= 15 else 1)


@pytest.mark.parametrize("model", sorted(PARAMS))
def test_each_camera_model_gives_back_the_models_pose(tmp_path, model):
    m = make_model(model, np.random.default_rng(2))
    write_binary(m, tmp_path)
    problem = colmap_problem(read_model(tmp_path), "frame_001.jpg")
    assert problem.n == 30 and problem.image_size == (640, 480)
    result = localize(problem, Options(backend="float64", min_invocations=0),
                      Float64Backend())
    assert result["status"] == "converged" and result["rms_px"] < 1e-4
    assert result["error"]["rotation_deg"] < 1e-4 and result["error"]["translation"] < 1e-5


def test_max_points_keeps_the_best_observed(opencv_model):
    root, _ = opencv_model
    problem = colmap_problem(read_model(root / "txt"), "frame_001.jpg", max_points=10)
    full = colmap_problem(read_model(root / "txt"), "frame_001.jpg")
    assert problem.n == 10
    kept = [int(np.flatnonzero((full.points3d == p).all(axis=1))[0]) for p in problem.points3d]
    assert all(k < 15 for k in kept)  # tracks of 2 before tracks of 1
    assert np.array_equal(problem.points2d, full.points2d[kept])


def test_the_command_line_localizes_a_colmap_image(opencv_model, tmp_path):
    root, _ = opencv_model
    saved = tmp_path / "p.json"
    out = CliRunner().invoke(client, [
        "localize", "--backend", "float64", "--json", "--colmap", str(root / "bin"),
        "--image-name", "frame_002.jpg", "--max-points", "8", "--save-problem", str(saved)])
    assert out.exit_code == 0, out.output
    record = json.loads(out.output)
    assert record["status"] == "converged" and record["error"]["translation"] < 1e-6
    assert len(json.loads(saved.read_text())["points3d"]) == 8


def _break(folder, name, edit):
    path = folder / name
    path.write_bytes(edit(path.read_bytes()))


def _replace(name, old, new, count=-1):
    return lambda f: _break(f, name, lambda b: b.replace(old, new, count))


def _drop_line(name, index):
    return lambda f: _break(f, name, lambda b: b"\n".join(
        line for k, line in enumerate(b.split(b"\n")) if k != index))


BAD = [
    ("txt", lambda f: (f / "points3D.txt").unlink(), "COLMAP model without points3D.txt"),
    ("txt", _replace("cameras.txt", b" 640 ", b" 64x "),
     "cameras.txt line 4: WIDTH: not an integer ('64x')"),
    ("txt", _replace("cameras.txt", b"OPENCV", b"OPENCV_FISHEYE"),
     "camera 1 model OPENCV_FISHEYE is not supported"),
    ("txt", _replace("cameras.txt", b"OPENCV", b"PINHOLE"),
     "cameras.txt line 4: PINHOLE has 4 parameters, got 8"),
    ("txt", _replace("cameras.txt", b"OPENCV", b"WEIRD"),
     "cameras.txt line 4: MODEL: unknown camera model 'WEIRD'"),
    ("txt", lambda f: _break(f, "images.txt", lambda b: b.rstrip(b"\n") + b" 1.0\n"),
     "images.txt line 7: POINTS2D of image 2"),
    ("txt", _replace("images.txt", b" 1 frame_001", b" 9 frame_001"),
     "image 'frame_001.jpg' refers to camera 9"),
    ("txt", _drop_line("points3D.txt", 3),
     "image 'frame_001.jpg' observes point 2, not in"),
    ("txt", _replace("points3D.txt", b" 128 128 128 ", b" 128 128 ", 1),
     "points3D.txt line 3: "),
    ("bin", lambda f: _break(f, "images.bin", lambda b: b[:-10]),
     "images.bin: image 2 points: file ends at byte"),
    ("bin", lambda f: _break(f, "points3D.bin", lambda b: b + b"\0\0"),
     "points3D.bin: 2 bytes after the last record"),
    ("bin", lambda f: _break(f, "cameras.bin",
                             lambda b: b[:12] + struct.pack("<i", 42) + b[16:]),
     "cameras.bin: camera 1: unknown camera model id 42"),
    ("bin", lambda f: _break(f, "images.bin", lambda b: b.replace(b".jpg\0", b".jpg")[:80]),
     "images.bin: image record 0: "),
    ("bin", lambda f: None, "--image-name: no image 'missing.jpg'"),
]


@pytest.mark.parametrize(("kind", "damage", "message"), BAD)
def test_a_malformed_model_is_exit_2_naming_the_file_and_field(opencv_model, tmp_path, kind,
                                                                damage, message):
    _, m = opencv_model
    folder = tmp_path / "model"
    (write_text if kind == "txt" else write_binary)(m, folder)
    damage(folder)
    name = "missing.jpg" if "missing.jpg" in message else "frame_001.jpg"
    out = CliRunner().invoke(client, ["localize", "--backend", "float64", "--colmap",
                                      str(folder), "--image-name", name])
    assert out.exit_code == 2, out.output
    assert out.stderr.count("\n") == 1 and "Traceback" not in out.output
    assert message in out.stderr, out.stderr


def test_an_empty_folder_and_too_few_matches_are_named(tmp_path):
    with pytest.raises(InputError, match="no COLMAP model"):
        read_model(tmp_path)
    m = make_model("PINHOLE", np.random.default_rng(3), n=3)
    write_text(m, tmp_path / "small")
    with pytest.raises(InputError, match="has 3 observations of model points"):
        colmap_problem(read_model(tmp_path / "small"), "frame_001.jpg")
