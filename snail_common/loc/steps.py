"""A fixed number of runs per frame: K Gauss-Newton or LM steps from a prediction.

The tracking schedule (schedule.py) gives every frame after the first exactly K secure
runs, whatever the data, so the count tells the servers nothing (a padded localization
hides it by running at least 20). Each run evaluates one pose; the client takes the step
the run's answer gives, in the clear:

- run 1 at the prediction p0: the cost there and the normal equations (or, when the
  circuit solves, the damped step);
- run i > 1 at the candidate (the accepted pose moved by the step held there): accepted
  when its cost is lower, and its model replaces the old one (LM's lambda follows the gain
  ratio, as in driver.py); else rejected: LM raises lambda and GN halves the step, from
  the same pose. When the client solves that costs no run; when the circuit solves, the
  next run is a "retry" at the same pose with the larger lambda;
- after the last run the answer is the accepted pose moved by the step held there. With
  K = 1 it is p0 plus the (lightly damped, for LM) Gauss-Newton step at p0.

No run sees the answer's cost, which is why a tracked frame is never "converged": the
offload client, which holds the points, checks the answer's fit in the clear (its
reprojection RMS); the map-owner device knows the cost at the last pose a run evaluated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .driver import LAMBDA_MAX, LAMBDA_MIN, LAMBDA_START, Caller, CallRecord, better
from .geometry import apply_step
from .quadratic import damped_step, predicted_reduction
from .types import IterationBackend, IterationResult, Normalized, Pose


@dataclass(frozen=True)
class Stepped:
    """K runs' answer: ``pose`` (never evaluated), the last pose a run accepted
    (``evaluated``, where ``cost`` is known) and the prediction's cost (``start_cost``)."""

    pose: Pose
    evaluated: Pose
    cost: float
    start_cost: float
    steps: int  # steps applied to reach ``pose``: accepted candidates and the final one
    invocations: int
    history: tuple[CallRecord, ...]


class _Held:
    """The pose a run accepted, its cost, and the step the client holds from it."""

    def __init__(self, pose: Pose, res: IterationResult, lam: float) -> None:
        self.pose, self.lam, self.nu, self.scale = pose, lam, 2.0, 1.0
        self.retry_due = False  # circuit solve: the next run re-damps at this pose
        self.take(pose, res)

    def take(self, pose: Pose, res: IterationResult) -> None:
        self.pose, self.cost, self.model, self.scale = pose, res.cost, res.normal, 1.0
        self.nu = 2.0
        self.step = (res.step if res.normal is None
                     else damped_step(res.normal.hess, res.normal.grad, self.lam))

    def candidate(self) -> Pose:
        """Where the held step leads (the same pose if the step is not finite)."""
        if not np.isfinite(self.step).all():
            return self.pose
        return apply_step(self.pose, self.scale * self.step)


def run_fixed(algorithm: str, nrm: Normalized, pose0: Pose, backend: IterationBackend,
              runs: int) -> Stepped:
    """Exactly ``runs`` backend calls from ``pose0`` (see the module doc)."""
    if runs < 1:
        raise ValueError(f"runs: at least 1, got {runs}")
    lm = algorithm == "lm"
    call = Caller(nrm, backend)
    held = _Held(pose0, call(pose0, LAMBDA_START if lm else 0.0, "start"),
                 LAMBDA_START if lm else 0.0)
    start_cost, accepted = held.cost, 0
    for _ in range(runs - 1):
        if held.retry_due:
            held.step, held.retry_due = call(held.pose, held.lam, "retry").step, False
            continue
        cand = held.candidate()
        lam = max(held.lam / 10.0, LAMBDA_MIN) if lm and held.model is None else held.lam
        res = call(cand, lam, "candidate")
        if better(res.cost, held.cost):
            call.mark_accepted()
            accepted += 1
            _accept(held, cand, res, lam, lm)
        else:
            _reject(held, lm)
    final = held.candidate()
    moved = final is not held.pose
    return Stepped(final, held.pose, float(held.cost), float(start_cost),
                   accepted + int(moved), len(call.history), tuple(call.history))


def _accept(held: _Held, cand: Pose, res: IterationResult, lam: float, lm: bool) -> None:
    """The candidate becomes the held pose; LM's lambda follows the gain ratio when the
    client holds the model (Nielsen, as driver.py), else the lambda it was called with."""
    if lm and held.model is not None:
        predicted = predicted_reduction(held.model, held.scale * held.step)
        rho = (held.cost - res.cost) / predicted if predicted != 0.0 else 0.0
        held.lam = min(max(held.lam * max(1 / 3, 1 - (2 * rho - 1) ** 3), LAMBDA_MIN),
                       LAMBDA_MAX)
    elif lm:
        held.lam = lam
    held.take(cand, res)


def _reject(held: _Held, lm: bool) -> None:
    """A candidate whose cost did not fall: LM damps more (a retry run when the circuit
    solves), GN halves the step."""
    if not lm:
        held.scale /= 2
    elif held.model is None:
        held.lam, held.retry_due = min(held.lam * 10.0, LAMBDA_MAX), True
    else:
        held.lam, held.nu = min(held.lam * held.nu, LAMBDA_MAX), 2 * held.nu
        held.step = damped_step(held.model.hess, held.model.grad, held.lam)

