"""The map-owner setting in the clear: what the map owner publishes and holds, and the
device's localization on map points it only holds under the map owner's pad.

The map owner publishes its sorted id list (the public index devices match against) and
the similarity that normalizes its map (centroid and RMS radius, as ``preprocess``
computes for a client's own points), and keeps every point as the float32 bits of its
normalized coordinates, 12 bytes a point: those are what the oblivious selection hands
the device under a pad P. The device's circuit inputs are then xyz ^ P (its share) and a
placeholder for P, whose wires the map owner feeds (its labels never reach the device).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from snail_common.pnp.spec import MASKED, OWNER_PAD, Spec

from .backends import Backend, Values, frame_inputs
from .geometry import pose_from_rvec_tvec, pose_to_rvec_tvec
from .mapfile import Frame, MapPoints
from .pipeline import Localized, Options, solve_fixed, solve_sil
from .preprocess import Frame as Similarity
from .preprocess import distortion_weights, undistort
from .problem import PoseVectors, Problem, ProblemError
from .types import Normalized

POINT_BYTES = 12  # three float32 words
TRANSFORM_BYTES = 32  # center (3) and scale, float64 little-endian


@dataclass(frozen=True)
class PublishedMap:
    """What anyone may know of a map: its ids, sorted, and its normalizing similarity."""

    ids: np.ndarray  # (M,) int64, ascending
    center: np.ndarray  # (3,)
    scale: float

    def transform_bytes(self) -> bytes:
        return np.array([*self.center, self.scale], "<f8").tobytes()

    @staticmethod
    def from_wire(ids: bytes, transform: bytes) -> PublishedMap:
        """From ``map_info``: ids as little-endian uint32, the transform as 4 float64."""
        values = np.frombuffer(transform, "<f8")
        id_arr = np.frombuffer(ids, "<u4").astype(np.int64)
        if len(values) != 4 or not np.isfinite(values).all() or not values[3] > 0:
            raise ValueError("map_info: the transform is not a finite center and a scale")
        if len(id_arr) and (np.diff(id_arr) <= 0).any():
            raise ValueError("map_info: the ids are not strictly ascending")
        return PublishedMap(id_arr, values[:3].copy(), float(values[3]))

    def ids_bytes(self) -> bytes:
        return self.ids.astype("<u4").tobytes()

    def positions(self, map_ids: np.ndarray) -> np.ndarray:
        """Each id's position in the sorted list (the device's secret selection indices);
        ProblemError naming the first id the map does not have."""
        pos = np.minimum(np.searchsorted(self.ids, map_ids), len(self.ids) - 1)
        missing = np.flatnonzero(self.ids[pos] != map_ids)
        if len(missing):
            i = int(missing[0])
            raise ProblemError(f"map_ids[{i}]: map point {int(map_ids[i])} is not in the "
                               f"map owner's map")
        return pos

    @property
    def similarity(self) -> Similarity:
        return Similarity(center=self.center, scale=self.scale, n_points=0)


def owner_values(points: MapPoints) -> tuple[PublishedMap, np.ndarray]:
    """The published part of a map and its points as (M, 12) bytes: float32 normalized
    coordinates, in id order."""
    order = np.argsort(points.ids, kind="stable")
    xyz = points.xyz[order]
    center = xyz.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((xyz - center) ** 2, axis=1))))
    if not scale > 1e-12 * max(1.0, float(np.abs(center).max())):
        raise ProblemError("points: all map points coincide")
    normalized = ((xyz - center) / scale).astype("<f4")
    return (PublishedMap(points.ids[order], center, scale),
            np.ascontiguousarray(normalized).view(np.uint8).reshape(-1, POINT_BYTES))


def _normalized(frame: Frame, world: np.ndarray) -> Normalized:
    """The frame as the circuit sees it, with ``world`` standing for its map points."""
    problem = Problem(K=frame.K, dist=frame.dist, points2d=frame.points2d,
                      points3d=np.zeros((frame.n, 3)), initial_pose=frame.initial_pose)
    image = undistort(problem)
    fx, fy = frame.K[0, 0], frame.K[1, 1]
    return Normalized(image=image, world=world, weights=distortion_weights(problem, image),
                      axis_weights=np.array([fx * fx, fy * fy]))


class SharedWorld:
    """A backend whose map points are the device's share xyz ^ P: every run's ``world``
    becomes ``world_masked`` and the map owner's ``world_pad`` gets zeros, a placeholder
    (the secure runner sends no label for those wires)."""

    name = "shared"

    def __init__(self, inner: Backend, masked: np.ndarray) -> None:
        self.inner, self.masked = inner, np.asarray(masked, np.uint32)

    @property
    def invocations(self) -> int:
        return self.inner.invocations

    def run(self, spec: Spec, values: Values) -> Values:
        shared = {k: v for k, v in values.items() if k != "world"}
        shared[MASKED] = self.masked
        shared[OWNER_PAD] = np.zeros_like(self.masked)
        return self.inner.run(spec, shared)

    def prepare(self, spec: Spec) -> None:
        self.inner.prepare(spec)

    def expect(self, spec: Spec, count: int, frame: Values | None = None) -> None:
        if frame is not None:  # the map points as run() passes them; the pad is not ours
            frame = {k: v for k, v in frame.items() if k != "world"} | {MASKED: self.masked}
        self.inner.expect(spec, count, frame)

    def pad(self, spec: Spec, target: int) -> None:
        self.inner.pad(spec, target)

    def traffic(self) -> dict[str, int]:
        return self.inner.traffic()


def localize_shared(frame: Frame, published: PublishedMap, masked: np.ndarray,
                    options: Options, backend: Backend, start: PoseVectors | None = None,
                    runs: int | None = None) -> Localized:
    """Refine the frame's pose on the map-owner circuit: the device's share ``masked``
    ((n, 3) uint32) is all it holds of its map points. From ``start`` (default: the
    frame's initial pose); ``runs``: exactly that many runs, the tracking schedule's frame
    (steps.py), instead of the padded localization."""
    spec = Spec(options.algorithm, "sil", options.solver, frame.n, owner=True,
                arith=options.arith_used)
    nrm = _normalized(frame, np.zeros((frame.n, 3)))
    return _localize(frame, published, nrm, spec, options, SharedWorld(backend, masked),
                     start, runs)


def localize_known(frame: Frame, published: PublishedMap, values: np.ndarray,
                   options: Options, backend: Backend, start: PoseVectors | None = None,
                   runs: int | None = None) -> Localized:
    """The same localization with the map points in the clear (the map owner's (M, 12)
    ``values``) on the plain SIL circuit: the oracle of ``localize_shared``."""
    points = values[published.positions(frame.map_ids)].copy().view("<f4")
    spec = Spec(options.algorithm, "sil", options.solver, frame.n, arith=options.arith_used)
    nrm = _normalized(frame, points.astype(np.float64))
    return _localize(frame, published, nrm, spec, options, backend, start, runs)


def _localize(frame: Frame, published: PublishedMap, nrm: Normalized, spec: Spec,
              options: Options, backend: Backend | SharedWorld,
              start_pose: PoseVectors | None, runs: int | None) -> Localized:
    """Padded (runs None) or exactly ``runs``. The RMS is the cost's, at the last pose a
    run evaluated: the device holds no 3D point to check the answer itself with."""
    start = time.perf_counter()
    similarity = Similarity(published.center, published.scale, frame.n)
    backend.prepare(spec)
    initial = start_pose or frame.initial_pose
    pose0 = similarity.to_normalized(pose_from_rvec_tvec(initial.rvec, initial.tvec))
    count = options.min_invocations if runs is None else runs
    # a tracked frame's runs take all their labels when invoked (pipeline.refine_fixed)
    backend.expect(spec, count, frame_inputs(spec, nrm) if runs is None else None)
    first = backend.invocations
    if runs is None:
        pose, cost, iterations, converged, walls = solve_sil(spec, options, backend, nrm,
                                                             pose0)
    else:
        stepped, walls = solve_fixed(spec, options, backend, nrm, pose0, runs)
        pose, cost, iterations, converged = (stepped.pose, stepped.cost, stepped.steps,
                                             False)
    backend.pad(spec, first + count)
    rvec, tvec = pose_to_rvec_tvec(similarity.to_original(pose))
    return Localized(rvec, tvec, cost, similarity.rms_px(cost), iterations,
                     backend.invocations - first, converged, walls, spec,
                     time.perf_counter() - start)
