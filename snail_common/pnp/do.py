"""The data-oblivious (DO) baseline: a fixed number of LM iterations in one program.

This is the paper's comparison point: the circuit cannot stop early or branch, so every
iteration runs: solve the damped normal equations, move the pose by a trig-free Cayley
update, evaluate the normal equations at the candidate, and obliviously keep the candidate
(pose, H, g, cost) iff its cost is lower, dividing lambda by 10 on acceptance and
multiplying it by 10 on rejection, clamped to [LAMBDA_MIN, LAMBDA_MAX]. Written once
against fops.F (circuit and mirror); ``do_reference`` is the same iteration in float64.

Cayley instead of exp: cay(w) = (I - [w]x / 2)^-1 (I + [w]x / 2)
                             = I + ([w]x + [w]x^2 / 2) / (1 + |w|^2 / 4),
an exact rotation that agrees with exp([w]x) to second order, so R' = cay(w) R,
t' = cay(w) t + v follows types.py's step convention.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np

from .fops import F, concat, const, stack
from .ldlt import ldlt_solve
from .normal import normal_equations
from .sil import Solver, damped
from .svd import DO_SWEEPS, REL_TOL, svd_solve

SOLVERS = ("ldlt", "svd")
ITERATIONS = 20
MAX_ITERATIONS = 99
LAMBDA_MIN = 1e-8
LAMBDA_MAX = 1e8
# previous_cost: the cost before the last iteration, so the client can tell whether the
# fixed budget ended at a stationary point (same cost tolerance as the SIL driver)
OUTPUT_SHAPES = {"R": (3, 3), "t": (3,), "cost": (), "previous_cost": ()}


@dataclass(frozen=True)
class State:
    """The LM state one iteration carries: pose, damping, and H, g, cost at the pose."""

    R: F
    t: F
    lam: F
    hess: F
    grad: F
    cost: F


def do_program(inputs: dict[str, F], solver: str, iterations: int = ITERATIONS,
               sweeps: int = DO_SWEEPS) -> dict[str, F]:
    """``iterations`` oblivious LM iterations from the input pose (inputs named as the SIL
    LM circuit's: R, t, lam, image, world, weights); returns the final pose, its cost and
    the cost before the last iteration."""
    *_, before, final = do_states(inputs, solver, iterations, sweeps)
    return {"R": final.R, "t": final.t, "cost": final.cost, "previous_cost": before.cost}


def do_states(inputs: dict[str, F], solver: str, iterations: int = ITERATIONS,
              sweeps: int = DO_SWEEPS) -> list[State]:
    """The state before every iteration and after the last (iterations + 1 states)."""
    if not 1 <= iterations <= MAX_ITERATIONS:
        raise ValueError(f"iterations must be in 1..{MAX_ITERATIONS}, got {iterations}")
    solve = _solver(solver, sweeps)
    data = (inputs["image"], inputs["world"], inputs["weights"])
    state = State(inputs["R"], inputs["t"], inputs["lam"],
                  *normal_equations(inputs["R"], inputs["t"], *data))
    states = [state]
    be = state.cost.be
    for k in range(iterations):
        before = be.and_gates()
        state = _iterate(state, data, solve)
        states.append(state)
        if k == 0:  # every iteration is the same gates on other wires: refuse early
            per_iteration = be.and_gates() - before
            be.expect_and(be.and_gates() + (iterations - 1) * per_iteration,
                          f"{iterations} LM iterations of {per_iteration:,} AND gates")
    return states


def _solver(name: str, sweeps: int) -> Solver:
    if name == "ldlt":
        return ldlt_solve
    if name == "svd":
        return partial(svd_solve, sweeps=sweeps)
    raise ValueError(f"solver must be one of {SOLVERS}, got {name!r}")


def _iterate(st: State, data: tuple[F, F, F], solve: Solver) -> State:
    with st.hess.be.shallow():  # the solve is one long chain: spend gates to cut depth
        step = solve(damped(st.hess, st.lam), -st.grad)
    R, t = cayley_update(st.R, st.t, step)
    hess, grad, cost = normal_equations(R, t, *data)
    accept = cost.lt(st.cost)
    old = concat([st.R[i] for i in range(3)] + [st.t, st.hess, st.grad, st.cost[None]])
    new = concat([R[i] for i in range(3)] + [t, hess, grad, cost[None]])
    kept = accept.select(old, new)
    be = st.lam.be
    lam = accept.select(st.lam * 10.0, st.lam * 0.1)
    lo, hi = const(be, LAMBDA_MIN), const(be, LAMBDA_MAX)
    lam = lam.lt(lo).select(lam, lo)
    lam = hi.lt(lam).select(lam, hi)
    return State(stack([kept[3 * i:3 * i + 3] for i in range(3)]), kept[9:12], lam,
                 kept[12:33], kept[33:39], kept[39])


def cayley_update(R: F, t: F, step: F) -> tuple[F, F]:
    """R' = cay(w) R, t' = cay(w) t + v for step = (v, w)."""
    v, w = step[0:3], step[3:6]
    i, j = [0, 1, 2, 0, 1, 2], [0, 1, 2, 1, 2, 0]  # w_i w_j: 3 squares, then 01, 12, 20
    p = w[i] * w[j]
    th2 = (p[0] + p[1]) + p[2]
    f = 1.0 / (th2 * 0.25 + 1.0)
    half = concat([p, th2[None]]) * 0.5
    h2 = half[6]
    # M = [w]x + (w w^T - |w|^2 I) / 2, row-major
    m = stack([half[0] - h2, half[3] - w[2], half[5] + w[1],
               half[3] + w[2], half[1] - h2, half[4] - w[0],
               half[5] - w[1], half[4] + w[0], half[2] - h2])
    fm = m * f
    q = stack([fm[0] + 1.0, fm[1], fm[2], fm[3], fm[4] + 1.0, fm[5], fm[6], fm[7],
               fm[8] + 1.0])
    q = stack([q[0:3], q[3:6], q[6:9]])
    rt = concat([R, t[:, None]], 1)  # (3, 4)
    moved = (q[:, :, None] * rt[None, :, :]).sum(1)
    return moved[:, 0:3], moved[:, 3] + v


def cayley64(w: np.ndarray) -> np.ndarray:
    """cay(w) in float64."""
    w = np.asarray(w, np.float64).reshape(3)
    k = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    return np.eye(3) + (k + k @ k / 2.0) / (1.0 + w @ w / 4.0)


def normal_equations64(R: np.ndarray, t: np.ndarray, image: np.ndarray, world: np.ndarray,
                       weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(J^T W J (6, 6), J^T W r (6,), r^T W r) in float64, types.py's conventions."""
    cam = np.asarray(world, np.float64) @ np.asarray(R, np.float64).T + t
    a, b, c = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2], 1.0 / cam[:, 2]
    zero = np.zeros_like(a)
    ju = np.stack([c, zero, -a * c, -a * b, 1 + a * a, -b], 1)
    jv = np.stack([zero, c, -b * c, -(1 + b * b), a * b, a], 1)
    err = np.stack([a, b], 1) - image
    w = np.asarray(weights, np.float64)
    hess = (ju * w[:, :1]).T @ ju + (jv * w[:, 1:]).T @ jv
    grad = (ju * (w[:, :1] * err[:, :1])).sum(0) + (jv * (w[:, 1:] * err[:, 1:])).sum(0)
    return hess, grad, float((w * err**2).sum())


def pinv_solve64(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    u, s, vt = np.linalg.svd(a)
    inv = np.where(s > REL_TOL * s.max(), 1.0 / np.where(s > 0, s, 1.0), 0.0)
    return vt.T @ (inv * (u.T @ b))


def do_reference(values: dict[str, np.ndarray], solver: str,
                 iterations: int = ITERATIONS) -> list[dict[str, np.ndarray | float]]:
    """The DO iteration in float64 (solves exact: np.linalg.solve for "ldlt", the
    thresholded pseudo-inverse for "svd"); returns the states as do_states does, each
    {"R", "t", "lam", "cost"}."""
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
    solve = np.linalg.solve if solver == "ldlt" else pinv_solve64
    data = (values["image"], values["world"], values["weights"])
    R, t = np.asarray(values["R"], np.float64), np.asarray(values["t"], np.float64)
    lam = float(values["lam"])
    hess, grad, cost = normal_equations64(R, t, *data)
    states: list[dict[str, np.ndarray | float]] = [{"R": R, "t": t, "lam": lam, "cost": cost}]
    for _ in range(iterations):
        step = solve(hess + lam * np.diag(np.diag(hess)), -grad)
        rot = cayley64(step[3:])
        cand_R, cand_t = rot @ R, rot @ t + step[:3]
        cand = normal_equations64(cand_R, cand_t, *data)
        if cand[2] < cost:
            R, t, (hess, grad, cost) = cand_R, cand_t, cand
            lam = max(lam / 10.0, LAMBDA_MIN)
        else:
            lam = min(lam * 10.0, LAMBDA_MAX)
        states.append({"R": R, "t": t, "lam": lam, "cost": cost})
    return states
