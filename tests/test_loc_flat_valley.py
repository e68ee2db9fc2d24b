"""LM on the client's normal equations reaches OpenCV's optimum where OpenCV does, within
the iteration cap, and says converged only there (issue 16). The scenes are the accuracy
sweep's (snail-bench accuracy) on which x10 / /10 LM with its cost-change stop failed."""

from __future__ import annotations

import pytest

from snail_bench.accuracy import scene
from snail_common.loc.accuracy import compare_with_opencv
from snail_common.loc.backends import MirrorBackend
from snail_common.loc.pipeline import Options, localize

PLANAR_SHARE = 0.25  # the sweep's default: scene k of a seed is the sweep's scene k
OPTIONS = Options("lm", min_invocations=0)


def _localize(seed: int, index: int):
    _, _, problem = scene(seed, index, PLANAR_SHARE)
    result = localize(problem, OPTIONS, MirrorBackend())
    return result, compare_with_opencv(problem, result.rvec, result.tvec)


@pytest.mark.parametrize(("seed", "index"), [(1, 256), (4, 858)])
def test_a_flat_valley_converges_within_the_cap(seed, index):
    """n = 4 planar scenes where lambda alternated between accepted and rejected values
    and the steps crawled: seed 1's ran into the 20-iteration cap at OpenCV's RMS but
    unconverged, seed 4's 0.02 px above OpenCV's. A rejected step is re-damped without
    a circuit run: the old two-pose cache re-ran the current pose after a second
    rejection (23 invocations for 20 iterations)."""
    n, planar, _ = scene(seed, index, PLANAR_SHARE)
    assert n == 4 and planar
    result, check = _localize(seed, index)
    assert result.converged and result.iterations < OPTIONS.max_iterations
    assert check["ok"], check
    assert result.invocations == result.iterations + 1


@pytest.mark.parametrize(("seed", "index"), [(4, 821), (1, 256), (4, 858)])
def test_converged_only_at_opencvs_optimum(seed, index):
    """Seed 4's scene 821 (n = 6, planar): one accepted step lowered the cost by less than
    cost_tol and the run stopped "converged" 0.9 % above OpenCV's RMS, where the normal
    equations still promised 1.5 % of the cost. A stop on the model's gain comes within
    1e-3 of OpenCV's RMS (cost_tol of the cost is 5e-5 of the RMS)."""
    result, check = _localize(seed, index)
    assert result.converged
    assert check["rms_px"] <= check["rms_opencv_px"] * (1 + 1e-3), check
