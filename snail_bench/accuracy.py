"""``snail-bench accuracy``: the client's LM/GN loop on the circuits' float32 mirror (held
bit-identical to the garbled circuits by tests/test_loc_circuits.py) against OpenCV's
iterative solvePnP from the same initial pose, over many random scenes.

The criterion (issue 16): our reprojection RMS is at most OpenCV's plus max(0.01 px,
0.5 %). Scenes: n log-uniform in [4, 256], 0.5 px noise, the initial pose 2-10 degrees
and 5-20 % of the distance off, a share of them planar (one tilted plane, like a tag).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from snail_common.loc.accuracy import compare_with_opencv
from snail_common.loc.backends import MirrorBackend
from snail_common.loc.pipeline import Options, localize
from snail_common.loc.synthetic import random_scene

MIN_POINTS, MAX_POINTS = 4, 256


def scene(seed: int, index: int, planar_share: float):
    """Scene ``index`` of the sweep with ``seed``: reproducible on its own."""
    rng = np.random.default_rng([seed, index])
    n = round(math.exp(rng.uniform(math.log(MIN_POINTS), math.log(MAX_POINTS))))
    planar = bool(rng.random() < planar_share)
    problem = random_scene(rng, n, rotation_deg=(2.0, 10.0),
                           translation_frac=float(rng.uniform(0.05, 0.20)), planar=planar)
    return n, planar, problem


def sweep(scenes: int, algorithm: str, seed: int = 1, planar_share: float = 0.25,
          solve: str | None = None, arith: str | None = None,
          tick: Callable[[], None] = lambda: None) -> dict:
    """Localize ``scenes`` random scenes; the pass rate, every failure, and every scene
    that ended unconverged (at the iteration cap, say) even where it passed."""
    options = Options(algorithm, solve=solve, min_invocations=0, arith=arith)
    backend = MirrorBackend()
    failures, passed, by_planar = [], 0, {"planar": [0, 0], "general": [0, 0]}
    iterations, invocations, unconverged = [], [], []
    for k in range(scenes):
        n, planar, problem = scene(seed, k, planar_share)
        result = localize(problem, options, backend)
        check = compare_with_opencv(problem, result.rvec, result.tvec)
        kind = by_planar["planar" if planar else "general"]
        kind[1] += 1
        iterations.append(result.iterations)
        invocations.append(result.invocations)
        if not result.converged:
            unconverged.append(k)
        if check["ok"]:
            passed += 1
            kind[0] += 1
        else:
            failures.append({"scene": k, "n": n, "planar": planar,
                             "rms_px": round(check["rms_px"], 5),
                             "rms_opencv_px": round(check["rms_opencv_px"], 5),
                             "iterations": result.iterations,
                             "converged": bool(result.converged)})
        tick()
    return {"algorithm": algorithm, "solve": options.solve_at, "arith": options.arith_used,
            "scenes": scenes,
            "seed": seed, "planar_share": planar_share, "passed": passed,
            "pass_rate": round(passed / scenes, 5),
            "passed_by_kind": {k: {"passed": v[0], "scenes": v[1]} for k, v in
                               by_planar.items()},
            "iterations": {"mean": round(float(np.mean(iterations)), 3),
                           "median": float(np.median(iterations)),
                           "max": int(max(iterations))},
            "invocations": {"mean": round(float(np.mean(invocations)), 3),
                            "max": int(max(invocations))},
            "not_converged": unconverged,
            "failures": failures}
