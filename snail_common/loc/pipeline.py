"""The one localization pipeline: a problem and a starting pose in, a refined pose out.

Every way of localizing runs through ``localize``: the client's ``localize`` and
``track`` commands (garbled or cleartext), the float64 reference, the mirror used for
accuracy sweeps. It preprocesses in the clear (undistort, normalize, pad), picks the
circuit, runs the iteration driver (SIL) or one data-oblivious invocation (DO) on a
backend, and maps the pose back to the problem's frame.

Privacy policy: the servers see how many invocations a frame makes, so a SIL frame makes
at least ``min_invocations``, padded with dummy runs (``Backend.pad``) when the driver
stops early. A DO frame is always one invocation, whatever the data. A frame of the
tracking schedule (``refine_fixed``, schedule.py) makes exactly K, each one step from a
prediction (steps.py): a count fixed before the data is seen hides as much.

Where the 6x6 system is solved (``solve``): by default in SIL mode the circuit returns
the normal equations and the client damps and solves them (sil.py says why that is safe
in the offload setting); ``circuit`` solves inside, as the paper does, and is the only
choice for DO. SIL circuits compute their per-point sums in fixed point by default
(``arith``, normal_fixed.py), or in narrow floats as before.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from snail_common.pnp.normal import UPPER
from snail_common.pnp.sil import ARITHS, CLIENT
from snail_common.pnp.spec import DO_ITERATIONS, DO_MAX_ITERATIONS, Spec

from .backends import Backend, frame_inputs, sil_values
from .driver import ALGORITHMS, COST_TOL, LAMBDA_START, run
from .geometry import pose_from_rvec_tvec, pose_to_rvec_tvec
from .preprocess import Frame as Similarity
from .preprocess import normalize, pad
from .problem import PoseVectors, Problem, check_in_front
from .quadratic import damped_step
from .reference import reprojection_rms
from .steps import Stepped, run_fixed
from .types import IterationBackend, IterationResult, NormalEquations, Normalized, Pose

MODES = ("sil", "do")
SOLVES = ("client", "circuit")


@dataclass(frozen=True)
class Options:
    """How to localize (the command line's choices; defaults are the product's)."""

    algorithm: str = "lm"
    # a tracked frame's step (refine_fixed): Gauss-Newton by default, as LM's damping
    # shortens the one step a frame gets (tracking.md: 76 against 90 % of hand-held
    # frames within 1 % of OpenCV's RMS at n = 6)
    step: str = "gn"
    mode: str = "sil"
    solver: str = "ldlt"
    max_iterations: int = 20
    min_invocations: int = 20
    pad_points: int = 0  # round n up to a multiple of this (0: no padding)
    do_iterations: int = DO_ITERATIONS
    solve: str | None = None  # client or circuit; None: client for sil, circuit for do
    arith: str | None = None  # per-point arithmetic, fixed or float; None: fixed for sil

    def __post_init__(self) -> None:
        if self.max_iterations < 1:
            raise ValueError("--max-iterations: must be at least 1")
        if self.min_invocations < 0 or self.pad_points < 0:
            raise ValueError("--min-invocations/--pad-points: must not be negative")
        if self.mode not in MODES:
            raise ValueError(f"--mode: expected sil or do, got {self.mode!r}")
        if self.algorithm not in ALGORITHMS or self.step not in ALGORITHMS:
            raise ValueError(f"--algorithm/--step: expected one of {ALGORITHMS}, got "
                             f"{self.algorithm!r}/{self.step!r}")
        if self.mode == "do" and self.algorithm != "lm":
            raise ValueError("--mode do: the data-oblivious baseline is LM only "
                             "(use --algorithm lm)")
        if not 1 <= self.do_iterations <= DO_MAX_ITERATIONS:
            raise ValueError(f"--do-iterations: must be in 1..{DO_MAX_ITERATIONS}")
        if self.solve not in (None, *SOLVES):
            raise ValueError(f"--solve: expected client or circuit, got {self.solve!r}")
        if self.arith not in (None, *ARITHS):
            raise ValueError(f"--arith: expected fixed or float, got {self.arith!r}")
        if self.arith == "fixed" and not self._fixed_possible:
            raise ValueError("--arith fixed: for --mode sil with the client's solve or "
                             "--solver ldlt")
        if self.mode == "do" and self.solve == "client":
            raise ValueError("--solve client: --mode do solves inside its circuit "
                             "(use --solve circuit)")

    @property
    def solve_at(self) -> str:
        """Where the step is solved: the client (default for sil) or the circuit."""
        return self.solve or ("circuit" if self.mode == "do" else "client")

    @property
    def _fixed_possible(self) -> bool:
        return self.mode == "sil" and (self.solve_at == "client" or self.solver == "ldlt")

    @property
    def arith_used(self) -> str:
        """The per-point arithmetic: fixed where the circuit has it, unless asked
        otherwise (the DO and SVD circuits are float only)."""
        return (self.arith or "fixed") if self._fixed_possible else "float"

    def circuit_points(self, n: int) -> int:
        if self.pad_points <= 1:
            return n
        return -(-n // self.pad_points) * self.pad_points

    def spec(self, n: int) -> Spec:
        """The circuit a problem of ``n`` points runs on."""
        iterations = self.do_iterations if self.mode == "do" else DO_ITERATIONS
        solver = CLIENT if self.solve_at == "client" else self.solver
        return Spec(self.algorithm, self.mode, solver, self.circuit_points(n), iterations,
                    arith=self.arith_used)


@dataclass(frozen=True)
class Localized:
    """A localized frame, in the problem's world frame."""

    rvec: np.ndarray
    tvec: np.ndarray
    cost: float
    rms_px: float
    iterations: int  # real LM/GN steps (the DO circuit's fixed count in mode do)
    invocations: int  # backend runs, padding included
    converged: bool
    walls: list[float]  # wall seconds of each timed (non-padding) invocation
    spec: Spec
    total_s: float


def localize(problem: Problem, options: Options, backend: Backend,
             initial: PoseVectors | None = None) -> Localized:
    """Refine the pose of ``problem`` from ``initial`` (default: the file's initial pose)
    on ``backend``."""
    start = time.perf_counter()
    nrm, frame, spec, pose0 = _prepared(problem, options, backend, initial)
    if options.mode == "sil":
        backend.expect(spec, options.min_invocations, frame_inputs(spec, nrm))
    else:
        backend.expect(spec, 1)
    first = backend.invocations
    solve = _solve_do if options.mode == "do" else solve_sil
    pose, cost, iterations, converged, walls = solve(spec, options, backend, nrm, pose0)
    if options.mode == "sil":
        backend.pad(spec, first + options.min_invocations)
    rvec, tvec = pose_to_rvec_tvec(frame.to_original(pose))
    return Localized(rvec, tvec, cost, reprojection_rms(problem, rvec, tvec), iterations,
                     backend.invocations - first, converged, walls, spec,
                     time.perf_counter() - start)


def refine_fixed(problem: Problem, options: Options, backend: Backend,
                 start_pose: PoseVectors, runs: int) -> Localized:
    """Exactly ``runs`` SIL invocations from ``start_pose`` (a tracking prediction), each
    one GN or LM step (steps.py): the tracking schedule's frame. Never ``converged``: the
    answer's own cost is not evaluated; its RMS here is computed in the clear.

    The frame's inputs are not declared shared by its runs (``expect`` without them): every
    session takes all its labels when invoked, as a padding run does. Declared, their
    labels would go ahead with each session, but every session needs its own anyway (no
    byte is saved), and the garble-ahead pool gives every session it holds to the frame,
    so the next frame, with other inputs, cancels those it did not use: at n = 6 and one
    run a frame that was a garbled session thrown away every other frame, 40-48 frames/s
    against 92-94 (two runs a frame: the same rate when quiet, 141 of 759 sessions
    thrown away on one of two runs)."""
    if options.mode != "sil":
        raise ValueError("--runs-per-frame: --mode do makes one run a frame already")
    start = time.perf_counter()
    nrm, frame, spec, pose0 = _prepared(problem, options, backend, start_pose)
    backend.expect(spec, runs)
    first = backend.invocations
    stepped, walls = solve_fixed(spec, options, backend, nrm, pose0, runs)
    backend.pad(spec, first + runs)  # a run that raised never returns here
    rvec, tvec = pose_to_rvec_tvec(frame.to_original(stepped.pose))
    return Localized(rvec, tvec, stepped.cost, reprojection_rms(problem, rvec, tvec),
                     stepped.steps, backend.invocations - first, False, walls, spec,
                     time.perf_counter() - start)


def _prepared(problem: Problem, options: Options, backend: Backend,
              initial: PoseVectors | None) -> tuple[Normalized, Similarity, Spec, Pose]:
    """The problem as its circuit takes it, the similarity back, the circuit (built or
    loaded now, not inside the first timed call) and the start in the circuit's frame."""
    pose_vectors = initial or problem.initial_pose
    if pose_vectors is None:
        raise ValueError("initial_pose: required for the first frame")
    check_in_front(problem, pose_vectors)
    nrm, frame = normalize(problem)
    spec = options.spec(problem.n)
    nrm = pad(nrm, spec.points) if spec.points != nrm.n else nrm
    backend.prepare(spec)
    pose0 = frame.to_normalized(pose_from_rvec_tvec(pose_vectors.rvec, pose_vectors.tvec))
    return nrm, frame, spec, pose0


def solve_sil(spec: Spec, options: Options, backend: Backend, nrm: Normalized,
              pose0: Pose) -> tuple[Pose, float, int, bool, list[float]]:
    """The LM/GN driver, one SIL invocation per call (per new pose, when the client
    solves); the map-owner setting drives it too (owner.py)."""
    walls: list[float] = []
    step_at = iteration_backend(spec, backend, walls)
    result = run(options.algorithm, nrm, pose0, step_at, options.max_iterations)
    return result.pose, float(result.cost), result.iterations, result.converged, walls


def solve_fixed(spec: Spec, options: Options, backend: Backend, nrm: Normalized,
                pose0: Pose, runs: int) -> tuple[Stepped, list[float]]:
    """Exactly ``runs`` SIL invocations from pose0, each an ``options.step`` step
    (steps.py; a GN step on a circuit that solves is its damped step at lambda 0), and
    their wall times."""
    walls: list[float] = []
    stepped = run_fixed(options.step, nrm, pose0, iteration_backend(spec, backend, walls), runs)
    return stepped, walls


def iteration_backend(spec: Spec, backend: Backend, walls: list[float]) -> IterationBackend:
    """One SIL invocation per call on ``backend``, timed into ``walls``: the normal
    equations solved here when the circuit returns them, else the circuit's step."""
    if spec.solver == CLIENT:
        return _ClientSolve(spec, backend, walls)

    def iteration(problem: Normalized, pose: Pose, lam: float) -> IterationResult:
        start = time.perf_counter()
        out = backend.run(spec, sil_values(spec, problem, pose, lam))
        walls.append(time.perf_counter() - start)
        return IterationResult(step=np.asarray(out["step"], np.float64),
                               cost=float(out["cost"]))

    return iteration


class _ClientSolve:
    """Iterations whose circuit returns the normal equations and the cost: the step is
    solved here, in float64, and the normal equations go to the driver, which re-damps a
    rejected LM step itself, so every call is a new pose and one invocation."""

    def __init__(self, spec: Spec, backend: Backend, walls: list[float]) -> None:
        self.spec, self.backend, self.walls = spec, backend, walls

    def __call__(self, problem: Normalized, pose: Pose, lam: float) -> IterationResult:
        start = time.perf_counter()
        out = self.backend.run(self.spec, sil_values(self.spec, problem, pose, lam))
        self.walls.append(time.perf_counter() - start)
        normal = NormalEquations(_symmetric(out["hess"]), np.asarray(out["grad"], np.float64))
        return IterationResult(step=damped_step(normal.hess, normal.grad, lam),
                               cost=float(out["cost"]), normal=normal)


def _symmetric(packed: np.ndarray) -> np.ndarray:
    """The 6x6 matrix of its upper triangle packed row-major (normal.UPPER)."""
    full = np.zeros((6, 6))
    rows, cols = np.array(UPPER).T
    full[rows, cols] = np.asarray(packed, np.float64)
    full[cols, rows] = full[rows, cols]
    return full


def _solve_do(spec: Spec, options: Options, backend: Backend, nrm: Normalized,
              pose0: Pose) -> tuple[Pose, float, int, bool, list[float]]:
    """One run of the data-oblivious circuit from pose0; converged when its last
    iteration changed the cost by at most the driver's tolerance."""
    values = sil_values(spec, nrm, pose0, LAMBDA_START)
    start = time.perf_counter()
    out = backend.run(spec, values)
    wall = time.perf_counter() - start
    cost, previous = float(out["cost"]), float(out["previous_cost"])
    converged = math.isfinite(cost) and previous - cost <= COST_TOL * previous
    pose = Pose(np.asarray(out["R"], np.float64), np.asarray(out["t"], np.float64))
    return pose, cost, spec.iterations, converged, [wall]
