"""Localize one image (or a sequence) and report a ``snail-result/1`` record.

The work is the localization pipeline (snail_common.loc.pipeline); this module picks its
backend: ``garbled`` (every invocation is garbled between the two servers; without
addresses both daemons start on loopback), ``cleartext`` (the same circuit evaluated in
the clear) or ``float64`` (the plain reference), and turns the result into the record.
"""

from __future__ import annotations

import contextlib
import os
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from snail_common.loc.backends import (
    Backend,
    CircuitBackend,
    Float64Backend,
    Values,
    interface,
    shared_bits,
)
from snail_common.loc.pipeline import Localized, refine_fixed
from snail_common.loc.pipeline import Options as PipelineOptions
from snail_common.loc.pipeline import localize as run_pipeline
from snail_common.loc.problem import PoseVectors, Problem
from snail_common.loc.reference import reprojection_rms
from snail_common.loc.schedule import MOTION_MODELS, ON_LOST
from snail_common.loc.trust import DEFAULT_MAX_RMS_PX, assess, degenerate, pose_error
from snail_common.net.linkrates import AUTO
from snail_common.pnp.spec import Spec

from .audit import DEFAULT_AUDIT_RATE, IntegrityFailure
from .blocking import SecureRunner
from .embedded import check_addresses, connected
from .links import DEFAULT_LINK_TIMEOUT
from .secure import DEFAULT_BUSY_WAIT
from .sessions import LINKS, FixedInputs

BACKENDS = ("garbled", "cleartext", "float64")
MAX_IN_FLIGHT = 16
RESULT_FORMAT = "snail-result/1"


@dataclass(frozen=True)
class Options(PipelineOptions):
    """The pipeline's options plus where its circuits run."""

    backend: str = "garbled"
    garbler: str | None = None
    evaluator: str | None = None
    tls_dir: str | None = None
    # the map-owner setting: reach the map owner through this evaluator (relay.py; its
    # EVALUATOR value: the one the runs go to), never directly
    relay: str | None = None
    busy_wait: float = DEFAULT_BUSY_WAIT
    link_timeout: float = DEFAULT_LINK_TIMEOUT
    scheme: str = AUTO
    max_rms_px: float = DEFAULT_MAX_RMS_PX
    cert_name: str = "client"
    audit_rate: float = DEFAULT_AUDIT_RATE  # share of runs the client garbles again
    evidence: str | None = None  # folder for the evidence of a caught garbler
    # a stream (track, Localizer.track): the fixed schedule (snail_common.loc.schedule)
    runs_per_frame: int = 1  # after the first frame; 0: every frame padded, as before
    in_flight: int | None = None  # frames whose runs overlap; None: from the round trip
    rate: float | None = None  # secure runs per second whatever the frames
    on_lost: str = "wait"
    motion_model: str = "auto"

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.backend not in BACKENDS:
            raise ValueError(f"--backend: expected one of {BACKENDS}, got {self.backend!r}")
        if not 0.0 <= self.audit_rate <= 1.0:
            raise ValueError(f"--audit-rate: expected a share in [0, 1], got "
                             f"{self.audit_rate!r}")
        check_addresses(self.garbler, self.evaluator, self.tls_dir)
        if self.runs_per_frame < 0:
            raise ValueError("--runs-per-frame: must not be negative")
        if self.in_flight is not None and not 1 <= self.in_flight <= MAX_IN_FLIGHT:
            raise ValueError(f"--in-flight: 1 to {MAX_IN_FLIGHT}, got {self.in_flight}")
        if self.rate is not None and not (self.rate > 0 and self.backend == "garbled"):
            raise ValueError("--rate: a rate above 0, with --backend garbled (there are "
                             "no servers to hide the frames' timing from otherwise)")
        if self.on_lost not in ON_LOST:
            raise ValueError(f"--on-lost: expected one of {ON_LOST}, got {self.on_lost!r}")
        if self.motion_model not in MOTION_MODELS:
            raise ValueError(f"--motion-model: expected one of {MOTION_MODELS}, got "
                             f"{self.motion_model!r}")
        if self.rate is not None and not self.runs_per_frame:
            raise ValueError("--rate: runs at a constant rate need --runs-per-frame >= 1")


class GarbledBackend(CircuitBackend):
    """Circuits garbled between the two servers through the client's secure runner."""

    def __init__(self, runner: SecureRunner) -> None:
        super().__init__(self._secure_run, "garbled")
        self.secure = runner
        self.on_invocation: Callable[[], object] | None = None  # e.g. a progress bar
        self.schemes: Counter[str] = Counter()  # sessions per garbling scheme so far
        self.frame: bytes | None = None  # the map owner's frame these runs are for

    def _secure_run(self, circuit_id: str, bits: np.ndarray) -> np.ndarray:
        run = self.secure.invoke(circuit_id, bits, self.frame)
        self.schemes[run.scheme] += 1
        out = run.outputs
        if self.on_invocation is not None:
            self.on_invocation()
        return out

    def expect(self, spec: Spec, count: int, frame: Values | None = None) -> None:
        """Garble ahead: the servers start on the frame's invocations before the client
        has their inputs (a padded frame makes at least ``count``), and the evaluator gets
        the labels of the ``frame``'s inputs with each session."""
        fixed = None if frame is None else FixedInputs(*shared_bits(interface(spec), frame))
        self.secure.expect(spec.registry_id, count, fixed)

    def pad(self, spec: Spec, target: int) -> None:
        """Runs on fresh random input bits until ``target`` invocations were made: the
        servers cannot tell them from real ones (the frame's inputs stay, so their labels
        went ahead as for a real run; the random pose makes the outputs noise)."""
        n_inputs = interface(spec).n_inputs
        fixed = self.secure.fixed(spec.registry_id)
        while self.invocations < target:
            noise = (np.frombuffer(os.urandom(n_inputs), np.uint8) & 1).astype(bool)
            if fixed is not None:
                noise[fixed.mask] = fixed.bits[fixed.mask]
            self.invocations += 1
            self._secure_run(spec.registry_id, noise)

    def pad_frame(self, spec: Spec, runs: int) -> None:
        """A frame of a stream with nothing to run (no usable points): the last frame's
        inputs declared again, so their labels reach the evaluator as a frame's do, and
        ``runs`` padding runs: the servers see a frame like any other."""
        fixed = self.secure.fixed(spec.registry_id)
        self.secure.expect(spec.registry_id, runs, fixed)
        self.pad(spec, self.invocations + runs)

    def traffic(self) -> dict[str, int]:
        return dict(self.secure.totals)


@contextlib.contextmanager
def backend_for(options: Options) -> Iterator[Backend]:
    """The backend ``options`` ask for; the garbled one is connected (to embedded daemons
    unless addresses are given) for the ``with`` block, and shared by a track's frames."""
    if options.backend == "float64":
        yield Float64Backend()
    elif options.backend == "cleartext":
        yield CircuitBackend()
    else:
        with connected(options.garbler, options.evaluator, options.tls_dir,
                       busy_wait=options.busy_wait, cert_name=options.cert_name,
                       link_timeout=options.link_timeout, scheme=options.scheme,
                       audit_rate=options.audit_rate,
                       evidence_dir=options.evidence) as (runner, _):
            yield GarbledBackend(runner)


def localize(problem: Problem, options: Options, backend: Backend,
             initial: PoseVectors | None = None) -> dict:
    """Solve one problem from ``initial`` (default: the file's initial pose) and return
    its snail-result/1 record, whose ``status`` says whether the pose can be trusted.
    Points that cannot determine a pose get a ``degenerate`` record and no circuit run."""
    start = initial or problem.initial_pose
    reason = degenerate(problem)
    if reason is not None and start is not None:
        return _degenerate_record(problem, options, start, reason)
    before, schemes = backend.traffic(), Counter(getattr(backend, "schemes", {}))
    retried, audited = _retries(backend), audit_counts(backend)
    try:
        result = run_pipeline(problem, options, backend, initial)
    except IntegrityFailure as exc:  # the frame's audits go with its failure
        exc.audits = audits_since(audited, audit_counts(backend))
        raise
    after = backend.traffic()
    schemes = Counter(getattr(backend, "schemes", {})) - schemes
    out = record(result, options, {link: after.get(link, 0) - before.get(link, 0)
                                   for link in LINKS}, problem, schemes)
    if isinstance(backend, GarbledBackend):
        out["retries"] = _retries(backend) - retried
        out["audits"] = audits_since(audited, audit_counts(backend))
    return out


def audit_counts(backend: Backend) -> dict[str, int]:
    """The garbled backend's audits so far: runs checked, audited, failed (audit.py)."""
    if isinstance(backend, GarbledBackend):
        return backend.secure.audits.counts()
    return {"runs": 0, "audited": 0, "failed": 0}


def audits_since(before: dict[str, int], after: dict[str, int]) -> dict[str, int]:
    return {k: after[k] - before.get(k, 0) for k in after}


def failure_record(exc: IntegrityFailure, options: Options) -> dict:
    """The snail-result/1 record of a frame that failed an integrity check: no pose, the
    party to blame (docs/formats.md)."""
    return {"format": RESULT_FORMAT, "status": "failed", "converged": False,
            "error": exc.record(), "audits": exc.audits, "backend": options.backend,
            "algorithm": options.algorithm, "mode": options.mode}


def track_frame(problem: Problem, options: Options, backend: Backend, start: PoseVectors,
                runs: int) -> dict:
    """A frame of the tracking schedule: exactly ``runs`` secure runs from ``start`` (a
    prediction), each one GN or LM step (pipeline.refine_fixed). Its record's status is
    ``tracked`` when the answer passes every check (never ``converged``: the answer's own
    cost was not evaluated), else why not; a degenerate frame makes no run here."""
    reason = degenerate(problem)
    if reason is not None:
        return _degenerate_record(problem, options, start, reason)
    before, schemes = backend.traffic(), Counter(getattr(backend, "schemes", {}))
    retried = _retries(backend)
    result = refine_fixed(problem, options, backend, start, runs)
    after = backend.traffic()
    schemes = Counter(getattr(backend, "schemes", {})) - schemes
    out = record(result, options, {link: after.get(link, 0) - before.get(link, 0)
                                   for link in LINKS}, problem, schemes, tracked=True)
    if isinstance(backend, GarbledBackend):
        out["retries"] = _retries(backend) - retried
    return out


def _retries(backend: Backend) -> int:
    """Secure runs the garbled backend ran again on another replica (0 for the others)."""
    return backend.secure.retries if isinstance(backend, GarbledBackend) else 0


def record(result: Localized, options: Options, traffic: dict[str, int],
           problem: Problem, schemes: Counter[str] | None = None,
           tracked: bool = False) -> dict:
    """The snail-result/1 record of a localized frame; ``schemes``: its sessions per
    garbling scheme (with ``--scheme auto`` each session's is picked on its own);
    ``tracked``: a frame of the fixed schedule (status ``tracked``, not ``converged``)."""
    status, warnings = assess(problem, result.rvec, result.tvec, result.converged,
                              result.rms_px, options.max_rms_px, tracked)
    out = {
        "format": RESULT_FORMAT,
        "rvec": [float(x) for x in result.rvec], "tvec": [float(x) for x in result.tvec],
        "status": status, "warnings": warnings,
        "converged": status == "converged", "iterations": result.iterations,
        "invocations": result.invocations, "cost": float(result.cost),
        "rms_px": result.rms_px,
        "algorithm": options.step if tracked else options.algorithm,  # what the runs took
        "mode": options.mode, "solve": options.solve_at, "arith": result.spec.arith,
        "solver": options.solver, "backend": options.backend,
        "timing": {"total_s": result.total_s, "per_iteration_s": result.walls},
        "traffic": traffic,
    }
    if problem.reference_pose is not None:
        out["error"] = pose_error(result.rvec, result.tvec, problem.reference_pose)
    if options.backend == "garbled":
        out["scheme"] = schemes.most_common(1)[0][0] if schemes else options.scheme
        if schemes and len(schemes) > 1:
            out["schemes"] = dict(schemes)
    if options.backend != "float64":
        iface = interface(result.spec)
        out["circuit"] = {"and": iface.counts["and"], "xor": iface.counts["xor"],
                          "depth": iface.depth, "points": result.spec.points}
    return out


def _degenerate_record(problem: Problem, options: Options, start: PoseVectors,
                       reason: str) -> dict:
    """The record of a frame whose points cannot determine a pose: the starting pose,
    unrefined, and no secure run (nothing about the frame reached the servers)."""
    out = {
        "format": RESULT_FORMAT,
        "rvec": start.rvec.tolist(), "tvec": start.tvec.tolist(),
        "status": "degenerate", "warnings": [reason],
        "converged": False, "iterations": 0, "invocations": 0, "cost": None,
        "rms_px": reprojection_rms(problem, start.rvec, start.tvec),
        "algorithm": options.algorithm, "mode": options.mode, "solve": options.solve_at,
        "solver": options.solver, "backend": options.backend,
        "timing": {"total_s": 0.0, "per_iteration_s": []},
        "traffic": dict.fromkeys(LINKS, 0),
    }
    if problem.reference_pose is not None:
        out["error"] = pose_error(start.rvec, start.tvec, problem.reference_pose)
    return out
