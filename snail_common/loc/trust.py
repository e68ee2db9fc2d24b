"""Whether a pose can be trusted, and inputs that cannot give one.

A solver that stops is not a solver that found the pose: a mirrored scene converges to a
pose with the map behind the camera, collinear points leave a rotation free, and a fit of
tens of pixels is a wrong match, not noise. The result says which (``status``, see
FORMATS.md), the command exits 3 for anything but a trusted status (``converged``, or
``tracked`` for a frame of the tracking schedule), and inputs that cannot determine a pose
are named before any circuit runs.
"""

from __future__ import annotations

import numpy as np

from .geometry import rvec_from_matrix, so3_exp
from .problem import PoseVectors, Problem

STATUSES = ("converged", "tracked", "not_converged", "degenerate", "bad_fit",
            "behind_camera")
# a pose to use: converged, or a tracked frame (a fixed number of steps from a prediction,
# steps.py) whose answer passed every check; its own cost was never evaluated
TRUSTED = ("converged", "tracked")
DEFAULT_MAX_RMS_PX = 8.0
MIN_POINTS = 4
FLAT = 1e-6  # second singular value / first below this: points on one line


def degenerate(problem: Problem) -> str | None:
    """Why the points cannot determine a pose, or None."""
    if problem.n < MIN_POINTS:
        return f"{problem.n} points: at least {MIN_POINTS} are needed for a pose"
    if _on_a_line(problem.points3d):
        return "the 3D points lie on one line: rotation about it is undetermined"
    if _on_a_line(problem.points2d):
        return ("the image points lie on one line: the map points lie on a plane through "
                "the camera centre")
    return None


def _on_a_line(points: np.ndarray) -> bool:
    centred = points - points.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    return bool(s[0] == 0 or s[1] / s[0] < FLAT)


def assess(problem: Problem, rvec: np.ndarray, tvec: np.ndarray, converged: bool,
           rms_px: float, max_rms_px: float = DEFAULT_MAX_RMS_PX,
           tracked: bool = False) -> tuple[str, list[str]]:
    """(status, warnings) of a solved pose: behind the camera, then not converged, then a
    bad fit, else converged (``tracked`` for a fixed-schedule frame, which never iterates
    to convergence); points projecting outside the image are a warning."""
    R = so3_exp(np.asarray(rvec, np.float64))
    cam = problem.points3d @ R.T + np.asarray(tvec, np.float64)
    warnings: list[str] = []
    behind = int(np.sum(~(cam[:, 2] > 0)))
    if problem.image_size is not None and not behind:
        u = cam[:, :2] / cam[:, 2:] @ problem.K[:2, :2].T + problem.K[:2, 2]
        width, height = problem.image_size
        outside = int(np.sum((u[:, 0] < -0.5) | (u[:, 0] > width - 0.5)
                             | (u[:, 1] < -0.5) | (u[:, 1] > height - 0.5)))
        if outside:
            warnings.append(f"{outside} of {problem.n} points project outside the "
                            f"{width}x{height} image")
    if behind:
        return "behind_camera", [f"{behind} of {problem.n} points end behind the camera",
                                 *warnings]
    if not converged and not tracked:
        return "not_converged", ["the iteration limit came before convergence", *warnings]
    if not rms_px <= max_rms_px:
        return "bad_fit", [f"reprojection RMS {rms_px:.2f} px is above --max-rms-px "
                           f"{max_rms_px:g}", *warnings]
    return ("tracked" if tracked else "converged"), warnings


def pose_error(rvec: np.ndarray, tvec: np.ndarray, reference: PoseVectors) -> dict:
    """Rotation (degrees) and camera-position (map units) error against a reference."""
    R, R_ref = so3_exp(np.asarray(rvec, np.float64)), so3_exp(reference.rvec)
    angle = float(np.degrees(np.linalg.norm(rvec_from_matrix(R @ R_ref.T))))  # exact
    # near 0, unlike arccos of the trace
    centre = -R.T @ np.asarray(tvec, np.float64)
    centre_ref = -R_ref.T @ reference.tvec
    return {"rotation_deg": angle, "translation": float(np.linalg.norm(centre - centre_ref))}
