"""Localize one image (or a sequence) and report a ``snail-result/1`` record.

Modes: ``sil`` (the product: the client's LM/GN driver, one secure single-iteration run
per step) and ``do`` (the paper's data-oblivious baseline: one secure run of a circuit
holding a fixed number of LM iterations; ``converged`` then says whether the last of them
changed the cost by at most the driver's cost tolerance).

Backends: ``garbled`` (every run is garbled between the two servers; without addresses
both daemons start on loopback), ``cleartext`` (the same circuit evaluated in the clear)
and ``float64`` (the plain reference: the LM/GN driver, or the DO iteration in float64),
for debugging.

Privacy policy: the servers see how many invocations a session makes, so a garbled SIL
session makes at least ``min_invocations``, padding with runs on fresh random input bits
(indistinguishable to the servers) when the driver stops early. A DO frame is always
exactly one invocation, whatever the data, so it needs no padding.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from snail_common.loc.backends import (
    BitRunner,
    CircuitIteration,
    cleartext_runner,
    compiled,
    interface,
    run_circuit,
    sil_values,
)
from snail_common.loc.circuits import DO_ITERATIONS, DO_MAX_ITERATIONS, Spec
from snail_common.loc.do import do_reference
from snail_common.loc.driver import COST_TOL, LAMBDA_START, run
from snail_common.loc.geometry import pose_from_rvec_tvec, pose_to_rvec_tvec
from snail_common.loc.preprocess import normalize, pad
from snail_common.loc.problem import PoseVectors, Problem, check_in_front
from snail_common.loc.reference import iteration_float64, reprojection_rms
from snail_common.loc.types import IterationBackend, Normalized, Pose

from .embedded import check_addresses, connected
from .secure import LINKS, SecureRunner

BACKENDS = ("garbled", "cleartext", "float64")
RESULT_FORMAT = "snail-result/1"


@dataclass(frozen=True)
class Options:
    """What the command line chooses; defaults are the product's defaults."""

    algorithm: str = "lm"
    mode: str = "sil"
    solver: str = "ldlt"
    backend: str = "garbled"
    max_iterations: int = 20
    min_invocations: int = 20
    pad_points: int = 0  # round n up to a multiple of this (0: no padding)
    garbler: str | None = None
    evaluator: str | None = None
    tls_dir: str | None = None
    do_iterations: int = DO_ITERATIONS

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"--backend: expected one of {BACKENDS}, got {self.backend!r}")
        if self.max_iterations < 1:
            raise ValueError("--max-iterations: must be at least 1")
        if self.min_invocations < 0 or self.pad_points < 0:
            raise ValueError("--min-invocations/--pad-points: must not be negative")
        if self.mode not in ("sil", "do"):
            raise ValueError(f"--mode: expected sil or do, got {self.mode!r}")
        if self.mode == "do" and self.algorithm != "lm":
            raise ValueError("--mode do: the data-oblivious baseline is LM only "
                             "(use --algorithm lm)")
        if not 1 <= self.do_iterations <= DO_MAX_ITERATIONS:
            raise ValueError(f"--do-iterations: must be in 1..{DO_MAX_ITERATIONS}")
        check_addresses(self.garbler, self.evaluator, self.tls_dir)

    def circuit_points(self, n: int) -> int:
        if self.pad_points <= 1:
            return n
        return -(-n // self.pad_points) * self.pad_points

    def spec(self, n: int) -> Spec:
        """The circuit a problem of ``n`` points runs on."""
        iterations = self.do_iterations if self.mode == "do" else DO_ITERATIONS
        return Spec(self.algorithm, self.mode, self.solver, self.circuit_points(n), iterations)


@dataclass(frozen=True)
class _Outcome:
    """A solved frame in the normalized frame, whichever mode solved it."""

    pose: Pose
    cost: float
    iterations: int
    converged: bool
    calls: int  # backend calls (secure invocations are counted by the runner)
    walls: list[float]


@contextlib.contextmanager
def secure_runner(options: Options) -> Iterator[SecureRunner | None]:
    """A connected runner for the garbled backend (embedded daemons unless addresses are
    given), or None for the debugging backends."""
    if options.backend != "garbled":
        yield None
        return
    with connected(options.garbler, options.evaluator, options.tls_dir) as (runner, _):
        yield runner


def _bit_runner(spec: Spec, options: Options, runner: SecureRunner | None) -> BitRunner:
    """How bits run: in the clear (this process compiles the circuit, now rather than in
    the first timed call) or garbled (this process only ever needs the interface)."""
    if options.backend == "cleartext":
        compiled(spec)
        return cleartext_runner
    if runner is None:
        raise ValueError("--backend garbled: needs a connected secure runner")
    return lambda cid, bits: runner.run(f"loc/{cid}", bits)


def _solve_sil(spec: Spec, options: Options, runner: SecureRunner | None, nrm: Normalized,
               pose0: Pose) -> _Outcome:
    """The client's LM/GN driver, one SIL run per step, padded to min_invocations."""
    backend: IterationBackend = iteration_float64 if options.backend == "float64" else \
        CircuitIteration(spec, _bit_runner(spec, options, runner))
    first_invocation = runner.invocations if runner else 0
    result = run(options.algorithm, nrm, pose0, backend, options.max_iterations)
    if runner is not None:
        _pad_invocations(runner, spec, first_invocation + options.min_invocations)
    return _Outcome(result.pose, float(result.cost), result.iterations, result.converged,
                    result.invocations, [call.wall_s for call in result.history])


def _solve_do(spec: Spec, options: Options, runner: SecureRunner | None, nrm: Normalized,
              pose0: Pose) -> _Outcome:
    """One run of the data-oblivious circuit (or its float64 reference) from pose0."""
    values = sil_values(spec, nrm, pose0, LAMBDA_START)
    if options.backend != "float64":
        bit_runner = _bit_runner(spec, options, runner)
        interface(spec)  # build or load before the clock starts, as SIL does
    start = time.perf_counter()
    if options.backend == "float64":
        *_, before, final = do_reference(values, spec.solver, spec.iterations)
        out = {"R": final["R"], "t": final["t"], "cost": final["cost"],
               "previous_cost": before["cost"]}
    else:
        out = run_circuit(spec, bit_runner, values)
    wall = time.perf_counter() - start
    cost, previous = float(out["cost"]), float(out["previous_cost"])
    converged = math.isfinite(cost) and previous - cost <= COST_TOL * previous
    pose = Pose(np.asarray(out["R"], np.float64), np.asarray(out["t"], np.float64))
    return _Outcome(pose, cost, spec.iterations, converged, 1, [wall])


def _pad_invocations(runner: SecureRunner, spec: Spec, target: int) -> None:
    """Dummy runs on fresh random input bits until the session made ``target`` runs."""
    n_inputs = interface(spec).n_inputs
    while runner.invocations < target:
        noise = np.frombuffer(os.urandom(n_inputs), np.uint8) & 1
        runner.run(spec.registry_id, noise.astype(bool))


def localize(problem: Problem, options: Options, runner: SecureRunner | None = None,
             initial: PoseVectors | None = None) -> dict:
    """Solve one problem from ``initial`` (default: the file's initial pose); the runner
    is required for the garbled backend and shared across the frames of a track."""
    start = time.perf_counter()
    pose_vectors = initial or problem.initial_pose
    if pose_vectors is None:
        raise ValueError("initial_pose: required for the first frame")
    check_in_front(problem, pose_vectors)
    nrm, frame = normalize(problem)
    spec = options.spec(problem.n)
    nrm = pad(nrm, spec.points) if spec.points != nrm.n else nrm
    first_invocation = runner.invocations if runner else 0
    totals_before = dict(runner.totals) if runner else {}
    pose0 = frame.to_normalized(pose_from_rvec_tvec(pose_vectors.rvec, pose_vectors.tvec))
    solve = _solve_do if options.mode == "do" else _solve_sil
    result = solve(spec, options, runner, nrm, pose0)
    rvec, tvec = pose_to_rvec_tvec(frame.to_original(result.pose))
    invocations = (runner.invocations - first_invocation) if runner else result.calls
    traffic = {link: (runner.totals.get(link, 0) - totals_before.get(link, 0)) if runner else 0
               for link in LINKS}
    record = {
        "format": RESULT_FORMAT,
        "rvec": [float(x) for x in rvec], "tvec": [float(x) for x in tvec],
        "converged": bool(result.converged), "iterations": result.iterations,
        "invocations": invocations, "cost": float(result.cost),
        "rms_px": reprojection_rms(problem, rvec, tvec),
        "algorithm": options.algorithm, "mode": options.mode, "solver": options.solver,
        "backend": options.backend,
        "timing": {"total_s": time.perf_counter() - start,
                   "per_iteration_s": result.walls},
        "traffic": traffic,
    }
    if options.backend != "float64":
        iface = interface(spec)
        record["circuit"] = {"and": iface.counts["and"], "xor": iface.counts["xor"],
                             "depth": iface.depth, "points": spec.points}
    return record
