"""COLMAP sparse models (text and binary: cameras, images, points3D) as localization
problems: one registered image's 2D-3D matches, its camera, and the model's pose as the
reference.

Our own reader (struct and numpy, following COLMAP's documented formats): pycolmap would
bring the whole COLMAP library as a binary wheel to read three small record formats.
Camera models map exactly onto OpenCV's distortion (SIMPLE_RADIAL k -> k1; RADIAL k1, k2;
OPENCV k1, k2, p1, p2; FULL_OPENCV adds k3..k6), which the problem carries; the client
undistorts with cv2.undistortPoints before any circuit (snail_common.loc.preprocess).
COLMAP puts the centre of the top-left pixel at (0.5, 0.5), OpenCV at (0, 0): points and
principal point move by half a pixel (the pose does not change).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from snail_common.loc.geometry import rvec_from_matrix
from snail_common.loc.problem import PoseVectors, Problem

from .camera import intrinsics
from .fields import InputError

# COLMAP's camera model ids: (name, number of parameters)
MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4),
          3: ("RADIAL", 5), 4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8),
          6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
          9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
          11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16)}
MODEL_IDS = {name: (model_id, count) for model_id, (name, count) in MODELS.items()}
SUPPORTED = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
_INT64 = (-(1 << 63), (1 << 63) - 1)  # ids are read into int64 arrays
FILES = ("cameras", "images", "points3D")
_OBSERVATION = np.dtype([("x", "<f8"), ("y", "<f8"), ("point3d_id", "<i8")])


@dataclass(frozen=True)
class ColmapCamera:
    id: int
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass(frozen=True)
class ColmapImage:
    id: int
    qvec: np.ndarray  # (w, x, y, z), world -> camera
    tvec: np.ndarray
    camera_id: int
    name: str
    xys: np.ndarray  # (n, 2) COLMAP pixels
    point3d_ids: np.ndarray  # (n,) int64, -1 for none


@dataclass(frozen=True)
class ColmapPoint:
    xyz: np.ndarray
    error: float
    track_length: int


@dataclass(frozen=True)
class Model:
    path: Path
    kind: str  # "bin" or "txt"
    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    points: dict[int, ColmapPoint]

    def file(self, name: str) -> Path:
        return self.path / f"{name}.{self.kind}"


def read_model(directory: str | Path) -> Model:
    """A COLMAP model folder, binary if cameras/images/points3D.bin are all there, else
    text; InputError naming the file, record and field at fault."""
    path = Path(directory)
    if not path.is_dir():
        raise InputError(f"{directory}: not a folder")
    for kind in ("bin", "txt"):
        present = [(path / f"{name}.{kind}").is_file() for name in FILES]
        if all(present):
            break
        if any(present):
            missing = [f"{name}.{kind}" for name, ok in zip(FILES, present) if not ok]
            raise InputError(f"{directory}: COLMAP model without {', '.join(missing)}")
    else:
        raise InputError(f"{directory}: no COLMAP model (cameras, images, points3D as .bin "
                         "or .txt)")
    reader = _Binary if kind == "bin" else _Text
    return Model(path, kind, reader(path / f"cameras.{kind}").cameras(),
                 reader(path / f"images.{kind}").images(),
                 reader(path / f"points3D.{kind}").points())


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None


def _model(model_id: int | str, where: str) -> tuple[str, int]:
    if isinstance(model_id, str):
        if model_id not in MODEL_IDS:
            raise InputError(f"{where}: unknown camera model {model_id!r}")
        return model_id, MODEL_IDS[model_id][1]
    if model_id not in MODELS:
        raise InputError(f"{where}: unknown camera model id {model_id}")
    return MODELS[model_id]


class _Binary:
    """COLMAP's little-endian records, read with a cursor that names what ran short."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.data = _read_bytes(path)
        self.at = 0

    def _take(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.at + size > len(self.data):
            raise InputError(f"{self.path}: {what}: file ends at byte {len(self.data)}")
        out = struct.unpack_from(fmt, self.data, self.at)
        self.at += size
        return out

    def _array(self, dtype: np.dtype, count: int, what: str) -> np.ndarray:
        size = dtype.itemsize * count
        if count < 0 or self.at + size > len(self.data):
            raise InputError(f"{self.path}: {what}: file ends at byte {len(self.data)}")
        out = np.frombuffer(self.data, dtype, count, self.at)
        self.at += size
        return out

    def _count(self, what: str) -> int:
        return self._take("<Q", what)[0]

    def _done(self) -> None:
        if self.at != len(self.data):
            raise InputError(f"{self.path}: {len(self.data) - self.at} bytes after the last "
                             "record")

    def cameras(self) -> dict[int, ColmapCamera]:
        out = {}
        for k in range(self._count("number of cameras")):
            what = f"camera record {k}"
            cam_id, model_id, width, height = self._take("<iiQQ", what)
            name, count = _model(model_id, f"{self.path}: camera {cam_id}")
            params = np.array(self._take(f"<{count}d", f"{what} parameters"))
            out[cam_id] = ColmapCamera(cam_id, name, width, height, params)
        self._done()
        return out

    def images(self) -> dict[int, ColmapImage]:
        out = {}
        for k in range(self._count("number of images")):
            what = f"image record {k}"
            image_id, *pose, camera_id = self._take("<i7di", what)
            end = self.data.find(b"\0", self.at)
            if end < 0:
                raise InputError(f"{self.path}: {what}: name without its terminating zero")
            try:
                name = self.data[self.at:end].decode()
            except UnicodeDecodeError:
                raise InputError(f"{self.path}: {what}: name is not UTF-8") from None
            self.at = end + 1
            count = self._count(f"image {image_id} number of points")
            obs = self._array(_OBSERVATION, count, f"image {image_id} points")
            out[image_id] = ColmapImage(
                image_id, np.array(pose[:4]), np.array(pose[4:]), camera_id, name,
                np.column_stack([obs["x"], obs["y"]]), obs["point3d_id"].astype(np.int64))
        self._done()
        return out

    def points(self) -> dict[int, ColmapPoint]:
        out = {}
        for k in range(self._count("number of points")):
            point_id, x, y, z, _, _, _, error, length = self._take("<Q3d3BdQ",
                                                                   f"point record {k}")
            self._array(np.dtype("<i4"), 2 * length, f"point {point_id} track")
            out[point_id] = ColmapPoint(np.array([x, y, z]), error, length)
        self._done()
        return out


class _Text:
    """COLMAP's text files: '#' comments, one record per line (two for an image)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            text = _read_bytes(path).decode()
        except UnicodeDecodeError:
            raise InputError(f"{path}: not UTF-8 text") from None
        self.lines = [(no, line.strip()) for no, line in enumerate(text.splitlines(), 1)
                      if not line.lstrip().startswith("#")]

    def _parse(self, no: int, tokens: list[str], types: str, names: list[str]) -> list:
        if len(tokens) < len(types):
            raise InputError(f"{self.path} line {no}: expected {len(types)} fields "
                             f"({' '.join(names)}), got {len(tokens)}")
        out = []
        for token, kind, name in zip(tokens, types, names):
            try:
                value = int(token) if kind == "i" else float(token) if kind == "f" else token
            except ValueError:
                raise InputError(f"{self.path} line {no}: {name}: not "
                                 f"{'an integer' if kind == 'i' else 'a number'} "
                                 f"({token[:20]!r})") from None
            if kind == "i" and not _INT64[0] <= value <= _INT64[1]:
                raise InputError(f"{self.path} line {no}: {name}: beyond 64 bits "
                                 f"({token[:20]!r}...)")
            out.append(value)
        return out

    def cameras(self) -> dict[int, ColmapCamera]:
        out = {}
        for no, line in self.lines:
            if not line:
                continue
            tokens = line.split()
            cam_id, model, width, height = self._parse(
                no, tokens, "isii", ["CAMERA_ID", "MODEL", "WIDTH", "HEIGHT"])
            name, count = _model(model, f"{self.path} line {no}: MODEL")
            if len(tokens) != 4 + count:
                raise InputError(f"{self.path} line {no}: {name} has {count} parameters, "
                                 f"got {len(tokens) - 4}")
            params = self._parse(no, tokens[4:], "f" * count,
                                 [f"PARAMS[{i}]" for i in range(count)])
            out[cam_id] = ColmapCamera(cam_id, name, width, height, np.array(params))
        return out

    def images(self) -> dict[int, ColmapImage]:
        out = {}
        lines = iter(self.lines)
        for no, line in lines:
            if not line:
                continue
            head = line.split(maxsplit=9)
            image_id, *pose, camera_id, name = self._parse(
                no, head, "ifffffffis",
                ["IMAGE_ID", "QW", "QX", "QY", "QZ", "TX", "TY", "TZ", "CAMERA_ID", "NAME"])
            points_no, points_line = next(lines, (no + 1, ""))
            tokens = points_line.split()
            if len(tokens) % 3:
                raise InputError(f"{self.path} line {points_no}: POINTS2D of image "
                                 f"{image_id}: {len(tokens)} numbers, not (X, Y, POINT3D_ID) "
                                 "triples")
            values = self._parse(points_no, tokens, "ffi" * (len(tokens) // 3),
                                 ["X", "Y", "POINT3D_ID"] * (len(tokens) // 3))
            triples = np.array(values, dtype=object).reshape(-1, 3)
            out[image_id] = ColmapImage(
                image_id, np.array(pose[:4]), np.array(pose[4:]), camera_id, name,
                triples[:, :2].astype(np.float64), triples[:, 2].astype(np.int64))
        return out

    def points(self) -> dict[int, ColmapPoint]:
        out = {}
        for no, line in self.lines:
            if not line:
                continue
            tokens = line.split()
            point_id, x, y, z, _, _, _, error = self._parse(
                no, tokens, "ifffiiif", ["POINT3D_ID", "X", "Y", "Z", "R", "G", "B", "ERROR"])
            if (len(tokens) - 8) % 2:
                raise InputError(f"{self.path} line {no}: TRACK of point {point_id}: not "
                                 "(IMAGE_ID, POINT2D_IDX) pairs")
            out[point_id] = ColmapPoint(np.array([x, y, z]), error, (len(tokens) - 8) // 2)
        return out


def opencv_camera(camera: ColmapCamera, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(K, dist) of a camera in OpenCV's pixel convention; InputError for models OpenCV's
    distortion cannot express."""
    p = camera.params
    if camera.model not in SUPPORTED:
        raise InputError(f"{where}: camera {camera.id} model {camera.model} is not supported "
                         f"(supported: {', '.join(SUPPORTED)})")
    if camera.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy, rest = p[1], p[2], p[3:]
    else:
        fx, fy, cx, cy, rest = p[0], p[1], p[2], p[3], p[4:]
    if not (fx > 0 and fy > 0):
        raise InputError(f"{where}: camera {camera.id}: focal length must be positive")
    dist = np.zeros(5)
    if camera.model in ("SIMPLE_RADIAL", "RADIAL"):
        dist[:len(rest)] = rest
    elif camera.model == "OPENCV":
        dist[:4] = rest
    elif camera.model == "FULL_OPENCV":
        dist = np.array(rest)
    return intrinsics(fx, fy, cx - 0.5, cy - 0.5), dist


def rotation_from_quaternion(q: np.ndarray) -> np.ndarray:
    """The rotation matrix of a (w, x, y, z) quaternion (normalized first)."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def colmap_problem(model: Model, image_name: str, max_points: int | None = None) -> Problem:
    """The problem of one registered image: its observations of model points (the
    ``max_points`` seen in most images, lower reprojection error first, when given), its
    camera, a first pose from EPnP in the clear and the model's pose as the reference."""
    found = [image for image in model.images.values() if image.name == image_name]
    images_file = model.file("images")
    if not found:
        names = sorted(image.name for image in model.images.values())
        shown = ", ".join(names[:5]) + (" ..." if len(names) > 5 else "")
        raise InputError(f"--image-name: no image {image_name!r} in {images_file} "
                         f"({len(names)} images: {shown})")
    image = found[0]
    if image.camera_id not in model.cameras:
        raise InputError(f"{images_file}: image {image_name!r} refers to camera "
                         f"{image.camera_id}, not in {model.file('cameras')}")
    camera = model.cameras[image.camera_id]
    K, dist = opencv_camera(camera, str(model.file("cameras")))
    rows = np.flatnonzero(image.point3d_ids >= 0)
    unknown = [int(i) for i in image.point3d_ids[rows] if int(i) not in model.points]
    if unknown:
        raise InputError(f"{images_file}: image {image_name!r} observes point {unknown[0]}, "
                         f"not in {model.file('points3D')}")
    points = [model.points[int(i)] for i in image.point3d_ids[rows]]
    if max_points is not None and len(rows) > max_points:
        order = sorted(range(len(rows)), key=lambda k: (-points[k].track_length,
                                                        points[k].error, k))[:max_points]
        keep = sorted(order)
        rows, points = rows[keep], [points[k] for k in keep]
    if len(rows) < 4:
        raise InputError(f"--image-name: image {image_name!r} has {len(rows)} observations "
                         "of model points; a pose needs at least 4")
    points2d = image.xys[rows] - 0.5
    points3d = np.array([p.xyz for p in points])
    R = rotation_from_quaternion(image.qvec)
    reference = PoseVectors(rvec_from_matrix(R), image.tvec.astype(np.float64))
    ok, rvec, tvec = cv2.solvePnP(points3d, points2d, K, dist, flags=cv2.SOLVEPNP_EPNP)
    if not ok:
        raise InputError(f"--image-name: EPnP found no first pose for {image_name!r}")
    return Problem(K=K, dist=dist, points2d=points2d, points3d=points3d,
                   initial_pose=PoseVectors(rvec.reshape(3), tvec.reshape(3)),
                   reference_pose=reference, image_size=(camera.width, camera.height))
