"""Iteration backends built on a localization circuit: encode the iteration's inputs, run
the circuit through some bit runner, decode step and cost.

The bit runner is the only thing that differs between the cleartext debug path
(``cleartext_runner``) and the garbled service (the client's secure runner): the
encoding, the circuit and the decoding are shared, so the two agree bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from snail_common.circuit import registry
from snail_common.circuit.cleartext import decode_outputs, encode_inputs, evaluate_bits
from snail_common.circuit.ir import Circuit, Interface
from snail_common.circuit.schedule import Schedule

from .circuits import Spec, run_mirror
from .types import IterationResult, Normalized, Pose

# (circuit id, input bits (n_inputs,)) -> output bits (n_outputs,)
BitRunner = Callable[[str, np.ndarray], np.ndarray]


def compiled(spec: Spec) -> tuple[Circuit, Schedule]:
    """The circuit of ``spec`` and its schedule (for evaluating it in the clear), through
    the registry's in-memory LRU and on-disk cache."""
    return registry.compiled(spec.registry_id)


def interface(spec: Spec) -> Interface:
    """All the client needs to encode, decode and name the circuit of ``spec``."""
    return registry.interface(spec.registry_id)


def sil_values(spec: Spec, problem: Normalized, pose: Pose, lam: float) -> dict[str, np.ndarray]:
    """The float32 inputs of a SIL circuit for one iteration at ``pose``, or of a DO circuit
    starting there (its inputs are named like the SIL LM circuit's)."""
    if problem.n != spec.points:
        raise ValueError(f"circuit {spec.circuit_id} takes {spec.points} points, "
                         f"the problem has {problem.n}")
    weights = np.asarray(problem.weights, float)[:, None] * np.asarray(problem.axis_weights, float)
    values = {"R": pose.R, "t": pose.t, "image": problem.image, "world": problem.world,
              "weights": weights}
    if spec.algorithm == "lm":
        values["lam"] = lam
    return {k: np.asarray(v, np.float32) for k, v in values.items()}


def cleartext_runner(circuit_id: str, bits: np.ndarray) -> np.ndarray:
    """Evaluate a localization circuit in the clear (debugging and tests)."""
    _, schedule = compiled(Spec.parse(circuit_id))
    return evaluate_bits(schedule, bits[None])[0]


def run_circuit(spec: Spec, runner: BitRunner, values: dict[str, np.ndarray]
                ) -> dict[str, np.ndarray]:
    """Encode ``values``, run the circuit of ``spec`` through ``runner``, decode the outputs."""
    iface = interface(spec)
    bits = encode_inputs(iface, values)[0]
    return decode_outputs(iface, runner(spec.circuit_id, bits))


class CircuitIteration:
    """An ``IterationBackend`` that runs the SIL circuit of ``spec`` through ``runner``."""

    def __init__(self, spec: Spec, runner: BitRunner = cleartext_runner) -> None:
        self.spec = spec
        self.runner = runner
        interface(spec)  # build or load now, not inside the first timed call

    def __call__(self, problem: Normalized, pose: Pose, lam: float) -> IterationResult:
        out = run_circuit(self.spec, self.runner, sil_values(self.spec, problem, pose, lam))
        return IterationResult(step=np.asarray(out["step"], np.float64),
                               cost=float(out["cost"]))


class MirrorIteration:
    """An ``IterationBackend`` on the float32 mirror: bit-identical to ``CircuitIteration``
    (tests hold them together) and fast enough for accuracy sweeps over many scenes."""

    def __init__(self, spec: Spec) -> None:
        self.spec = spec

    def __call__(self, problem: Normalized, pose: Pose, lam: float) -> IterationResult:
        out = run_mirror(self.spec, sil_values(self.spec, problem, pose, lam))
        return IterationResult(step=np.asarray(out["step"], np.float64),
                               cost=float(out["cost"]))
