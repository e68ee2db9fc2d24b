"""Backends: what runs a localization circuit, one ``run`` call per invocation.

The localization pipeline (pipeline.py) builds a circuit's named inputs and reads its
named outputs; a backend decides how the circuit is computed:
- ``Float64Backend``: the same algorithm in float64 (the plain reference, for debugging);
- ``MirrorBackend``: the numpy float32 mirror, bit-identical to the circuit and fast
  enough for accuracy sweeps over thousands of scenes;
- ``CircuitBackend``: the circuit itself, its bits run by a ``BitRunner``: evaluated in
  the clear by default, garbled between the two servers with the client's secure runner
  (snail_client), so cleartext and garbled runs agree bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from snail_common.circuit import registry
from snail_common.circuit.cleartext import decode_outputs, encode_inputs, evaluate_bits
from snail_common.circuit.ir import Circuit, Interface
from snail_common.circuit.schedule import Schedule
from snail_common.pnp import family
from snail_common.pnp.do import do_reference, normal_equations64, pinv_solve64
from snail_common.pnp.normal import UPPER
from snail_common.pnp.normal_fixed import decode, map_fixed, weight_unit, weights_fixed
from snail_common.pnp.sil import CLIENT, ITERATION_INPUTS, takes_map_as_integers
from snail_common.pnp.spec import Spec, integer_outputs, run_mirror

from .geometry import hat, so3_exp
from .types import Normalized, Pose

Values = dict[str, np.ndarray]
# (circuit id as servers know it, input bits (n_inputs,)) -> output bits (n_outputs,)
BitRunner = Callable[[str, np.ndarray], np.ndarray]


def compiled(spec: Spec) -> tuple[Circuit, Schedule]:
    """The circuit of ``spec`` and its schedule, through the registry's in-memory LRU and
    on-disk cache."""
    registry.register(family.FAMILY)
    return registry.compiled(spec.registry_id)


def interface(spec: Spec) -> Interface:
    """All a client needs to encode, decode and name the circuit of ``spec``."""
    registry.register(family.FAMILY)
    return registry.interface(spec.registry_id)


def sil_values(spec: Spec, problem: Normalized, pose: Pose, lam: float) -> Values:
    """The inputs of a SIL circuit for one iteration at ``pose``, or of a DO circuit
    starting there (float64; circuit and mirror round them to float32)."""
    if problem.n != spec.points:
        raise ValueError(f"circuit {spec.circuit_id} takes {spec.points} points, "
                         f"the problem has {problem.n}")
    weights = np.asarray(problem.weights, float)[:, None] * np.asarray(problem.axis_weights, float)
    values = {"R": pose.R, "t": pose.t, "image": problem.image, "world": problem.world,
              "weights": weights}
    if spec.algorithm == "lm" and spec.solver != CLIENT:
        values["lam"] = lam
    values = {k: np.asarray(v, np.float64) for k, v in values.items()}
    if spec.arith == "fixed":
        values["wfix"] = weights_fixed(values["weights"])
    if takes_map_as_integers(spec.solver, spec.arith):  # "world" stays for Float64Backend
        values["wmap"], values["emap"] = map_fixed(values["world"])
    return values


def frame_inputs(spec: Spec, problem: Normalized) -> Values:
    """The inputs every SIL invocation of a frame shares: all but the pose and damping."""
    values = sil_values(spec, problem, Pose(np.eye(3), np.zeros(3)), 0.0)
    return {k: v for k, v in values.items() if k not in ITERATION_INPUTS}


def _wires(iface: Interface, names: Callable[[str], bool]) -> np.ndarray:
    """The input wires (bool mask) of the groups whose name ``names`` accepts."""
    return np.repeat([names(g.name) for g in iface.inputs], [g.size for g in iface.inputs])


def frame_wires(iface: Interface) -> np.ndarray:
    """The input wires of a frame's inputs (bool mask): those ``frame_inputs`` keeps."""
    return _wires(iface, lambda name: name not in ITERATION_INPUTS)


def shared_bits(iface: Interface, frame: Values) -> tuple[np.ndarray, np.ndarray]:
    """Which input wires ``frame`` covers (bool mask) and their bits (zeros elsewhere)."""
    placeholders = {g.name: np.zeros(g.shape) for g in iface.inputs
                    if g.name not in frame}
    bits = encode_inputs(iface, {**placeholders, **_own(iface, frame)})[0]
    mask = _wires(iface, frame.__contains__)
    return mask, bits & mask


def _own(iface: Interface, values: Values) -> Values:
    """The values the circuit takes: sil_values also carries the float32 map, which the
    Float64Backend reads and a circuit taking the map as integers does not."""
    names = {g.name for g in iface.inputs}
    return {k: v for k, v in values.items() if k in names}


def circuit_outputs(spec: Spec, values: Values, out: Values) -> Values:
    """A circuit's outputs as the float circuit names them: fixed-point sums decoded with
    the weights they were computed with; the in-circuit solve's cost, of the normalized
    weights, times their unit. The fixed-point circuits rotate about the map's origin
    (normal_fixed.py): their sums and steps come back in types.py's terms here."""
    if integer_outputs(spec):
        sums = decode(values["weights"], int(values["emap"]), out)
        hess, grad = about_camera(_full(sums["hess"]), sums["grad"], values["t"])
        return {**sums, "hess": hess[tuple(np.array(UPPER).T)], "grad": grad}
    if spec.arith == "fixed":
        return {**out, "step": step_about_camera(out["step"], values["t"]),
                "cost": np.float64(out["cost"]) * weight_unit(values["weights"])}
    return out


def about_camera(hess: np.ndarray, grad: np.ndarray,
                 t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """J^T W J (6, 6) and J^T W r of the step (v', w) that rotates about the map's origin,
    t' = t + v', as those of types.py's (v, w), t' = exp(w) t + v: to first order
    v' = v - [t]x w, so J = J' T with T = [[I, -[t]x], [0, I]]. In float64 this loses
    nothing of what the circuit computed, however ill-conditioned the result (one tag far
    away: rotation and translation nearly alike, which is why the circuit does not sum
    them so)."""
    T = np.eye(6)
    T[:3, 3:] = -hat(np.asarray(t, np.float64))
    return T.T @ hess @ T, T.T @ grad


def step_about_camera(step: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The step (v', w) about the map's origin (R' = exp(w) R, t' = t + v') as types.py's
    (v, w), exactly: v = t + v' - exp(w) t."""
    step = np.asarray(step, np.float64)
    t = np.asarray(t, np.float64)
    return np.concatenate([t + step[:3] - so3_exp(step[3:]) @ t, step[3:]])


def _full(packed: np.ndarray) -> np.ndarray:
    full = np.zeros((6, 6))
    rows, cols = np.array(UPPER).T
    full[rows, cols] = np.asarray(packed, np.float64)
    full[cols, rows] = full[rows, cols]
    return full


class Backend:
    """Runs localization circuits; counts its invocations."""

    name = ""

    def __init__(self) -> None:
        self.invocations = 0

    def run(self, spec: Spec, values: Values) -> Values:
        """One invocation of the circuit of ``spec`` on named inputs: its named outputs."""
        self.invocations += 1
        return self._run(spec, values)

    def _run(self, spec: Spec, values: Values) -> Values:
        raise NotImplementedError

    def prepare(self, spec: Spec) -> None:
        """Build or load what running ``spec`` needs, before any invocation is timed."""

    def expect(self, spec: Spec, count: int, frame: Values | None = None) -> None:
        """At least ``count`` invocations of ``spec`` are coming, all with the inputs in
        ``frame`` (a backend that can do work ahead of its inputs may start now)."""

    def pad(self, spec: Spec, target: int) -> None:
        """Dummy invocations until ``target`` have been made, where someone watches how
        many there are (the servers); nothing to do for a local backend."""

    def traffic(self) -> dict[str, int]:
        """Bytes per link so far (none for a local backend)."""
        return {}


class Float64Backend(Backend):
    """The circuit's algorithm in float64: SIL solves exactly, DO iterates in float64."""

    name = "float64"

    def _run(self, spec: Spec, values: Values) -> Values:
        if spec.mode == "do":
            *_, before, final = do_reference(values, spec.solver, spec.iterations)
            return {"R": final["R"], "t": final["t"], "cost": np.float64(final["cost"]),
                    "previous_cost": np.float64(before["cost"])}
        hess, grad, cost = normal_equations64(values["R"], values["t"], values["image"],
                                              values["world"], values["weights"])
        if spec.solver == CLIENT:
            return {"hess": hess[tuple(np.array(UPPER).T)], "grad": grad,
                    "cost": np.float64(cost)}
        lam = float(values.get("lam", 0.0))
        solve = np.linalg.solve if spec.solver == "ldlt" else pinv_solve64
        step = solve(hess + lam * np.diag(np.diag(hess)), -grad)
        return {"step": step, "cost": np.float64(cost)}


class MirrorBackend(Backend):
    """The numpy float32 mirror: the circuit's outputs bit for bit, without gates."""

    name = "mirror"

    def _run(self, spec: Spec, values: Values) -> Values:
        return circuit_outputs(spec, values, run_mirror(spec, values))


def cleartext_runner(circuit_id: str, bits: np.ndarray) -> np.ndarray:
    """Evaluate a registered circuit in the clear (debugging and tests)."""
    registry.register(family.FAMILY)
    _, schedule = registry.compiled(circuit_id)
    return evaluate_bits(schedule, bits[None])[0]


class CircuitBackend(Backend):
    """The circuit: encode the inputs, run the bits through ``runner``, decode."""

    name = "cleartext"

    def __init__(self, runner: BitRunner = cleartext_runner, name: str = "cleartext") -> None:
        super().__init__()
        self.runner, self.name = runner, name

    def prepare(self, spec: Spec) -> None:
        if self.runner is cleartext_runner:
            compiled(spec)  # this process evaluates it
        else:
            interface(spec)  # the servers evaluate it: the layout is enough here

    def _run(self, spec: Spec, values: Values) -> Values:
        iface = interface(spec)
        bits = encode_inputs(iface, _own(iface, values))[0]
        return circuit_outputs(spec, values,
                               decode_outputs(iface, self.runner(spec.registry_id, bits)))
