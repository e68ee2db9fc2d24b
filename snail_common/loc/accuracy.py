"""Accuracy against OpenCV from the same initial pose: the issue's acceptance criterion is a
reprojection RMS no worse than OpenCV's by more than max(0.01 px, 0.5 %)."""

from __future__ import annotations

import cv2
import numpy as np

from .problem import Problem
from .reference import reprojection_rms

ABS_TOL_PX = 0.01
REL_TOL = 0.005


def tolerance(rms_opencv: float) -> float:
    return max(ABS_TOL_PX, REL_TOL * rms_opencv)


def _initial(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    if problem.initial_pose is None:
        raise ValueError("initial_pose: missing (OpenCV needs the same starting pose)")
    return (problem.initial_pose.rvec.reshape(3, 1).copy(),
            problem.initial_pose.tvec.reshape(3, 1).copy())


def opencv_iterative(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """cv2.solvePnP(SOLVEPNP_ITERATIVE) refining the initial pose."""
    rvec, tvec = _initial(problem)
    ok, rvec, tvec = cv2.solvePnP(problem.points3d, problem.points2d, problem.K, problem.dist,
                                  rvec, tvec, useExtrinsicGuess=True,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise RuntimeError("cv2.solvePnP failed")
    return rvec.reshape(3), tvec.reshape(3)


def opencv_refine_lm(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """cv2.solvePnPRefineLM from the initial pose (OpenCV's default criteria)."""
    rvec, tvec = _initial(problem)
    rvec, tvec = cv2.solvePnPRefineLM(problem.points3d, problem.points2d, problem.K,
                                      problem.dist, rvec, tvec)
    return rvec.reshape(3), tvec.reshape(3)


def compare_with_opencv(problem: Problem, rvec: np.ndarray, tvec: np.ndarray) -> dict:
    """Our pose's RMS against OpenCV's two refiners; `ok` is the issue's criterion against
    solvePnP iterative, `ok_refine_lm` the same against solvePnPRefineLM."""
    rms = reprojection_rms(problem, rvec, tvec)
    rms_cv = reprojection_rms(problem, *opencv_iterative(problem))
    rms_lm = reprojection_rms(problem, *opencv_refine_lm(problem))
    return {"rms_px": rms, "rms_opencv_px": rms_cv, "rms_refine_lm_px": rms_lm,
            "ok": rms <= rms_cv + tolerance(rms_cv),
            "ok_refine_lm": rms <= rms_lm + tolerance(rms_lm)}
