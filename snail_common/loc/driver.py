"""The client's LM / GN loop around "one iteration" (secure, cleartext or float64).

A backend call at a pose returns the cost AT that pose and the step FROM it, and, when the
client solves (the default), the normal equations H = J^T W J and g = J^T W r there: the
cost's quadratic model cost + 2 g.d + d^T H d (the cost is r^T W r, not half of it).

Counting: an *iteration* is one trial step (one candidate pose evaluated, accepted or not),
at most max_iterations of them; *invocations* are backend calls, each a circuit run: the
start, one per iteration, and, when the circuit returns only the step, one per retry.

LM when the client holds the normal equations. It damps and solves the step itself, so a
rejected step is re-damped with no call (no invocation). Lambda follows the gain ratio
rho = actual / predicted reduction (Nielsen): on accept lambda *= max(1/3, 1 - (2 rho -
1)^3), on reject lambda *= nu, nu *= 2. x10 / /10 alternated between an accepted and a
rejected lambda in the flat valleys of near-planar n = 4 scenes and crawled to the cap
(one scene in two of four 1,000-scene sweeps, 0.02 px above OpenCV on one); Nielsen
settles lambda where steps are accepted (at most 15 iterations over the 4,000 scenes, mean
3.2 against 3.3). It stops, converged, when nothing measurable is left: the model's best
(undamped) step gains at most cost_tol of the cost (g^T H^-1 g, infinite unless H is
positive definite: the circuit's narrow sums can tip a near-singular H, and a stop on
that ended 37 % above OpenCV on one scene) or is relatively smaller than step_tol.
Undamped, because a damped step is small as much because lambda is large as because the
optimum is near. The model replaces the cost-change stop: one accepted step that lowered
the cost by under cost_tol stopped a run 0.9 % above OpenCV's RMS while the model still
promised 1.5 % of the cost.

LM when the circuit returns only the step (the in-circuit solve): the candidate pose is
called with lambda / 10 already, in the hope of acceptance; if its cost is not lower, the
step is rejected and the old pose is called again with lambda * 10 (a "retry" call).
Converged when an accepted step lowered the cost by a relative cost_tol or less, or the
next step is relatively smaller than step_tol.

Both: lambda starts at 1e-3 (the usual LM start: mostly Gauss-Newton while the model is
good) and is clamped to [1e-8, 1e8]: below 1e-8 damping is lost in float32 rounding of
diag(H), above 1e8 the step is below any tolerance anyway. A rejected candidate whose cost
equals the current one within cost_tol stops converged (no progress is measurable at the
backend's precision); a rejection at lambda_max stops without convergence. The tolerances
sit above float32 noise: a circuit's cost carries a relative error up to ~1e-5 when the
residuals are small against the image coordinates (cancellation in a - u), so cost_tol =
1e-4 and step_tol = 1e-5 (1e-5 rad is 0.008 px at f = 800, and the RMS is second order in
that: ~1e-4 px).

GN (lambda = 0) as the paper runs it has no rejection: every step is taken, and the
result is the best pose seen, so a diverging GN run still reports its best point. That GN
oscillates on about one real frame in ten, so the product's GN is safeguarded: a step
that does not lower the cost is halved (a new candidate, one more invocation) up to four
times before the run stops. It stops on the same rules as LM: on the model's gain and
best step when the client holds the normal equations, else on the cost change and step.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from .geometry import apply_step
from .quadratic import damped_step, gain, predicted_reduction
from .types import IterationBackend, IterationResult, Normalized, Pose

ALGORITHMS = ("lm", "gn")
LAMBDA_START = 1e-3
LAMBDA_MIN = 1e-8
LAMBDA_MAX = 1e8
COST_TOL = 1e-4
STEP_TOL = 1e-5
MIN_STEP_SCALE = 1 / 16  # the safeguarded GN's shortest try: four halvings


@dataclass(frozen=True)
class CallRecord:
    """One backend call: where it was made (start, candidate, retry or halved), with which
    lambda (for the client's solve: the one the step to this pose was damped with), the
    cost it returned, whether its pose became the current pose, and its wall time."""

    kind: str
    lam: float
    cost: float
    accepted: bool
    wall_s: float


@dataclass(frozen=True)
class DriverResult:
    pose: Pose  # in the frame of the Normalized problem the driver was given
    cost: float
    iterations: int
    invocations: int
    converged: bool
    history: tuple[CallRecord, ...]


def relative_step(step: np.ndarray, pose: Pose) -> float:
    """Step size relative to the pose: translation against |t| (at least 1, the map's RMS
    radius in the normalized frame), rotation in radians."""
    v, w = step[:3], step[3:]
    return max(float(np.linalg.norm(v)) / max(float(np.linalg.norm(pose.t)), 1.0),
               float(np.linalg.norm(w)))


class Caller:
    """Times and records backend calls."""

    def __init__(self, nrm: Normalized, backend: IterationBackend) -> None:
        self.nrm, self.backend = nrm, backend
        self.history: list[CallRecord] = []

    def __call__(self, pose: Pose, lam: float, kind: str) -> IterationResult:
        start = time.perf_counter()
        res = self.backend(self.nrm, pose, lam)
        self.history.append(CallRecord(kind, lam, float(res.cost), kind == "start",
                                       time.perf_counter() - start))
        return res

    def mark_accepted(self) -> None:
        last = self.history[-1]
        self.history[-1] = CallRecord(last.kind, last.lam, last.cost, True, last.wall_s)


def better(new: float, old: float) -> bool:
    """A finite cost below the old one (a NaN from a broken circuit never wins)."""
    return math.isfinite(new) and new < old


def run_lm(nrm: Normalized, pose0: Pose, backend: IterationBackend, max_iterations: int = 20,
           *, lam0: float = LAMBDA_START, lam_min: float = LAMBDA_MIN,
           lam_max: float = LAMBDA_MAX, cost_tol: float = COST_TOL,
           step_tol: float = STEP_TOL) -> DriverResult:
    """Levenberg-Marquardt with accept/reject (see the module doc): damped by the gain
    ratio when the backend returns the normal equations, by x10 / /10 when only steps."""
    call = Caller(nrm, backend)
    limits = _Limits(max_iterations, lam_min, lam_max, cost_tol, step_tol)
    lam = min(max(lam0, lam_min), lam_max)
    start = call(pose0, lam, "start")
    loop = _lm_on_steps if start.normal is None else _lm_on_model
    pose, cost, iterations, converged = loop(call, pose0, start, lam, limits)
    return DriverResult(pose, cost, iterations, len(call.history), converged,
                        tuple(call.history))


@dataclass(frozen=True)
class _Limits:
    max_iterations: int
    lam_min: float
    lam_max: float
    cost_tol: float
    step_tol: float


def _lm_on_steps(call: Caller, pose: Pose, res: IterationResult, lam: float,
                 limits: _Limits) -> tuple[Pose, float, int, bool]:
    """The circuit returns only the damped step: a candidate is called with lambda / 10
    already, and a rejected step costs a retry call at lambda * 10."""
    cost, step = res.cost, res.step
    iterations, converged = 0, relative_step(step, pose) <= limits.step_tol
    while not converged and iterations < limits.max_iterations:
        cand, lam_next = apply_step(pose, step), max(lam / 10.0, limits.lam_min)
        res = call(cand, lam_next, "candidate")
        iterations += 1
        if better(res.cost, cost):
            call.mark_accepted()
            converged = (cost - res.cost <= limits.cost_tol * cost
                         or relative_step(res.step, cand) <= limits.step_tol)
            pose, cost, step, lam = cand, res.cost, res.step, lam_next
            continue
        if _indistinguishable(res.cost, cost, limits.cost_tol):
            converged = True
        elif lam >= limits.lam_max or iterations >= limits.max_iterations:
            break
        else:
            lam = min(lam * 10.0, limits.lam_max)
            step = call(pose, lam, "retry").step
            converged = relative_step(step, pose) <= limits.step_tol
    return pose, cost, iterations, converged


def _lm_on_model(call: Caller, pose: Pose, res: IterationResult, lam: float,
                 limits: _Limits) -> tuple[Pose, float, int, bool]:
    """The client holds the normal equations: steps are damped here, a rejected one is
    re-damped with no call, and lambda follows the gain ratio (Nielsen)."""
    cost, normal, nu = res.cost, res.normal, 2.0
    step = damped_step(normal.hess, normal.grad, lam)
    iterations = 0
    converged = _settled(res, pose, limits.cost_tol, limits.step_tol)
    while not converged and iterations < limits.max_iterations:
        cand = apply_step(pose, step)
        res = call(cand, lam, "candidate")
        iterations += 1
        if better(res.cost, cost):
            call.mark_accepted()
            predicted = predicted_reduction(normal, step)
            # rho < 0 (a model tipped non-convex at the noise floor) raises lambda steeply
            rho = (cost - res.cost) / predicted if predicted != 0.0 else 0.0
            lam = min(max(lam * max(1 / 3, 1 - (2 * rho - 1) ** 3), limits.lam_min),
                      limits.lam_max)
            pose, cost, normal, nu = cand, res.cost, res.normal, 2.0
            step = damped_step(normal.hess, normal.grad, lam)
            converged = _settled(res, pose, limits.cost_tol, limits.step_tol)
            continue
        if _indistinguishable(res.cost, cost, limits.cost_tol):
            converged = True
        elif lam >= limits.lam_max:
            break
        else:
            lam, nu = min(lam * nu, limits.lam_max), 2 * nu
            step = damped_step(normal.hess, normal.grad, lam)  # same pose, same model
    return pose, cost, iterations, converged


def _settled(res: IterationResult, pose: Pose, cost_tol: float, step_tol: float) -> bool:
    """Nothing measurable left at ``pose``, where ``res`` was returned: the next step is
    below step_tol or, when the normal equations are known, the model's best (undamped)
    step is, or gains at most cost_tol of the cost. Undamped: a damped step is small
    because lambda is large as much as because the optimum is near."""
    if res.normal is None:
        return relative_step(res.step, pose) <= step_tol
    best = damped_step(res.normal.hess, res.normal.grad, 0.0)
    return relative_step(best, pose) <= step_tol or gain(res.normal) <= cost_tol * res.cost


def _indistinguishable(new: float, old: float, cost_tol: float) -> bool:
    """A rejected candidate's cost equal to the current one at the backend's precision."""
    return abs(new - old) <= cost_tol * old


def run_gn(nrm: Normalized, pose0: Pose, backend: IterationBackend, max_iterations: int = 20,
           *, cost_tol: float = COST_TOL, step_tol: float = STEP_TOL,
           safeguard: bool = True) -> DriverResult:
    """Gauss-Newton (lambda = 0), reporting the best pose seen. Safeguarded (default): a
    step that does not lower the cost is halved, down to MIN_STEP_SCALE; unguarded (the
    paper's GN): every finite step is taken."""
    call = Caller(nrm, backend)
    pose, res = pose0, call(pose0, 0.0, "start")
    best_pose, best_cost = pose, res.cost
    cost, step, scale = res.cost, res.step, 1.0
    iterations, converged = 0, _settled(res, pose, cost_tol, step_tol)
    while not converged and iterations < max_iterations:
        cand = apply_step(pose, scale * step)
        res = call(cand, 0.0, "candidate" if scale == 1.0 else "halved")
        iterations += 1
        if not math.isfinite(res.cost) and not safeguard:
            break
        if safeguard and not better(res.cost, cost):
            if _indistinguishable(res.cost, cost, cost_tol):
                converged = True
            elif scale > MIN_STEP_SCALE:
                scale /= 2
                continue
            break
        call.mark_accepted()
        converged = ((res.normal is None and abs(cost - res.cost) <= cost_tol * cost)
                     or _settled(res, cand, cost_tol, step_tol))
        pose, cost, step, scale = cand, res.cost, res.step, 1.0
        if cost < best_cost:
            best_pose, best_cost = pose, cost
    return DriverResult(best_pose, best_cost, iterations, len(call.history), converged,
                        tuple(call.history))


def run(algorithm: str, nrm: Normalized, pose0: Pose, backend: IterationBackend,
        max_iterations: int = 20) -> DriverResult:
    """Dispatch on the algorithm name of the command line ("lm" or "gn")."""
    if algorithm == "lm":
        return run_lm(nrm, pose0, backend, max_iterations)
    if algorithm == "gn":
        return run_gn(nrm, pose0, backend, max_iterations)
    raise ValueError(f"algorithm: expected one of {ALGORITHMS}, got {algorithm!r}")
