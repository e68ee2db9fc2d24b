"""``snail-bench accuracy``: the client's LM/GN loop on the circuits' float32 mirror (held
bit-identical to the garbled circuits by tests/test_loc_circuits.py) against OpenCV's
iterative solvePnP and against the same loop in float64, from the same initial pose, over
many synthetic scenes.

The criterion (issue 16): our reprojection RMS is at most OpenCV's plus max(0.01 px,
0.5 %); against float64 (issue 32) the same tolerance on the float64 loop's RMS, so a
scene the algorithm itself cannot solve from its start does not count against the
circuit. Scene kinds: ``random`` (n log-uniform in [4, 256], 0.5 px noise, the initial
pose 2-10 degrees and 5-20 % of the distance off, a share of them planar: one tilted
plane, like a tag), and the kinds real frames bring (loc/hard_scenes.py): ``one-tag``,
``plane-tags`` and ``far-few``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from snail_common.loc.accuracy import compare_with_opencv, tolerance
from snail_common.loc.backends import Float64Backend, MirrorBackend
from snail_common.loc.hard_scenes import KINDS as HARD_KINDS
from snail_common.loc.hard_scenes import hard_scene
from snail_common.loc.pipeline import Options, localize
from snail_common.loc.problem import Problem
from snail_common.loc.synthetic import random_scene

MIN_POINTS, MAX_POINTS = 4, 256
KINDS = ("random", *HARD_KINDS)


def scene(seed: int, index: int, planar_share: float):
    """Scene ``index`` of the random sweep with ``seed``: reproducible on its own."""
    rng = np.random.default_rng([seed, index])
    n = round(math.exp(rng.uniform(math.log(MIN_POINTS), math.log(MAX_POINTS))))
    planar = bool(rng.random() < planar_share)
    problem = random_scene(rng, n, rotation_deg=(2.0, 10.0),
                           translation_frac=float(rng.uniform(0.05, 0.20)), planar=planar)
    return n, planar, problem


def kind_scene(kind: str, seed: int, index: int, planar_share: float) -> tuple[str, Problem]:
    """Scene ``index`` of a sweep of ``kind`` and the group it is counted in
    (``passed_by_kind``: planar or general for random scenes, else the kind)."""
    if kind == "random":
        _, planar, problem = scene(seed, index, planar_share)
        return ("planar" if planar else "general"), problem
    return kind, hard_scene(kind, np.random.default_rng([seed, index]))


def _stats(values: list[int]) -> dict:
    return {"mean": round(float(np.mean(values)), 3), "median": float(np.median(values)),
            "max": int(max(values))}


def sweep(scenes: int, algorithm: str, seed: int = 1, planar_share: float = 0.25,
          solve: str | None = None, arith: str | None = None,
          tick: Callable[[], None] = lambda: None, kind: str = "random") -> dict:
    """Localize ``scenes`` scenes of ``kind`` on the mirror and in float64; the pass rates
    against OpenCV and against float64, every failure (against either), and every scene
    that ended unconverged (at the iteration cap, say) even where it passed."""
    if kind not in KINDS:
        raise ValueError(f"kind: expected one of {', '.join(KINDS)}, got {kind!r}")
    options = Options(algorithm, solve=solve, min_invocations=0, arith=arith)
    backend, reference = MirrorBackend(), Float64Backend()
    failures = []
    groups = {"planar": [0, 0], "general": [0, 0]} if kind == "random" else {kind: [0, 0]}
    passed = passed_f64 = f64_passed = 0
    iterations, invocations, unconverged, f64_iterations = [], [], [], []
    for k in range(scenes):
        group, problem = kind_scene(kind, seed, k, planar_share)
        result = localize(problem, options, backend)
        f64 = localize(problem, options, reference)
        check = compare_with_opencv(problem, result.rvec, result.tvec)
        cv = check["rms_opencv_px"]
        reaches = result.rms_px <= f64.rms_px + tolerance(f64.rms_px)
        counts = groups[group]
        counts[1] += 1
        iterations.append(result.iterations)
        invocations.append(result.invocations)
        f64_iterations.append(f64.iterations)
        f64_passed += f64.rms_px <= cv + tolerance(cv)
        passed_f64 += reaches
        if not result.converged:
            unconverged.append(k)
        if check["ok"]:
            passed += 1
            counts[0] += 1
        if not (check["ok"] and reaches):
            failures.append({"scene": k, "n": problem.n, "planar": group == "planar",
                             "rms_px": round(check["rms_px"], 5),
                             "rms_opencv_px": round(cv, 5),
                             "rms_float64_px": round(f64.rms_px, 5),
                             "iterations": result.iterations,
                             "float64_iterations": f64.iterations,
                             "converged": bool(result.converged)})
        tick()
    return {"kind": kind, "algorithm": algorithm, "solve": options.solve_at,
            "arith": options.arith_used, "scenes": scenes, "seed": seed,
            "planar_share": planar_share, "passed": passed,
            "pass_rate": round(passed / scenes, 5),
            "passed_float64": passed_f64, "pass_rate_float64": round(passed_f64 / scenes, 5),
            "passed_by_kind": {k: {"passed": v[0], "scenes": v[1]} for k, v in
                               groups.items()},
            "iterations": _stats(iterations),
            "invocations": {"mean": round(float(np.mean(invocations)), 3),
                            "max": int(max(invocations))},
            "not_converged": unconverged,
            "float64": {"passed": f64_passed, "iterations": _stats(f64_iterations)},
            "failures": failures}
