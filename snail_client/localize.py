"""Localize one image (or a sequence) with the client's LM/GN driver, one secure SIL
iteration per step, and report a ``snail-result/1`` record.

Backends: ``garbled`` (the product: every iteration is a garbled run between the two
servers; without addresses both daemons start on loopback), ``cleartext`` (the same
circuit evaluated in the clear) and ``float64`` (the plain reference), for debugging.

Privacy policy: the servers see how many invocations a session makes, so a garbled
session makes at least ``min_invocations``, padding with runs on fresh random input bits
(indistinguishable to the servers) when the driver stops early.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from snail_common.loc.backends import CircuitIteration, compiled
from snail_common.loc.circuits import Spec
from snail_common.loc.driver import run
from snail_common.loc.geometry import pose_from_rvec_tvec, pose_to_rvec_tvec
from snail_common.loc.preprocess import normalize, pad
from snail_common.loc.problem import PoseVectors, Problem, check_in_front
from snail_common.loc.reference import iteration_float64, reprojection_rms
from snail_common.loc.types import IterationBackend

from .embedded import embedded_services
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

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"--backend: expected one of {BACKENDS}, got {self.backend!r}")
        if self.max_iterations < 1:
            raise ValueError("--max-iterations: must be at least 1")
        if self.min_invocations < 0 or self.pad_points < 0:
            raise ValueError("--min-invocations/--pad-points: must not be negative")
        if self.mode != "sil":
            raise ValueError("--mode: only 'sil' is served yet; the data-oblivious baseline "
                             "is built and measured by `snail-bench circuit --mode do`")
        remote = (self.garbler, self.evaluator, self.tls_dir)
        if any(remote) and not all(remote):
            raise ValueError("--garbler, --evaluator and --tls-dir go together")

    def circuit_points(self, n: int) -> int:
        if self.pad_points <= 1:
            return n
        return -(-n // self.pad_points) * self.pad_points


@contextlib.contextmanager
def secure_runner(options: Options) -> Iterator[SecureRunner | None]:
    """A connected runner for the garbled backend (embedded daemons unless addresses are
    given), or None for the debugging backends."""
    if options.backend != "garbled":
        yield None
        return
    if options.garbler:
        with SecureRunner(options.garbler, options.evaluator, options.tls_dir) as runner:
            yield runner
        return
    with embedded_services() as services, SecureRunner(
            services.garbler_addr, services.evaluator_addr, services.tls_dir) as runner:
        yield runner


def _backend(spec: Spec, options: Options, runner: SecureRunner | None) -> IterationBackend:
    if options.backend == "float64":
        return iteration_float64
    if options.backend == "cleartext":
        return CircuitIteration(spec)
    assert runner is not None
    return CircuitIteration(spec, lambda cid, bits: runner.run(f"loc/{cid}", bits))


def _pad_invocations(runner: SecureRunner, spec: Spec, target: int) -> None:
    """Dummy runs on fresh random input bits until the session made ``target`` runs."""
    circuit, _ = compiled(spec)
    while runner.invocations < target:
        noise = np.frombuffer(os.urandom(circuit.n_inputs), np.uint8) & 1
        runner.run(f"loc/{spec.circuit_id}", noise.astype(bool))


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
    spec = Spec(options.algorithm, options.mode, options.solver,
                options.circuit_points(problem.n))
    nrm = pad(nrm, spec.points) if spec.points != nrm.n else nrm
    first_invocation = runner.invocations if runner else 0
    totals_before = dict(runner.totals) if runner else {}
    backend = _backend(spec, options, runner)
    pose0 = frame.to_normalized(pose_from_rvec_tvec(pose_vectors.rvec, pose_vectors.tvec))
    result = run(options.algorithm, nrm, pose0, backend, options.max_iterations)
    if runner is not None:
        _pad_invocations(runner, spec, first_invocation + options.min_invocations)
    rvec, tvec = pose_to_rvec_tvec(frame.to_original(result.pose))
    invocations = (runner.invocations - first_invocation) if runner else result.invocations
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
                   "per_iteration_s": [call.wall_s for call in result.history]},
        "traffic": traffic,
    }
    if options.backend != "float64":
        circuit, _ = compiled(spec)
        counts = circuit.counts()
        record["circuit"] = {"and": counts["and"], "xor": counts["xor"],
                             "depth": circuit.depth(), "points": spec.points}
    return record
