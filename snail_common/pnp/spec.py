"""Localization circuits by name: what each computes (``Spec``), its netlist, its mirror.

A circuit id names everything that shapes the circuit, e.g. ``lm-sil-ldlt-n6``; the
registry knows it as ``loc/lm-sil-ldlt-n6`` (family.py registers the family). The circuit
that returns the normal equations for the client to solve (solver ``client``) is the
same for LM and GN: ``ne-sil-n6``. With the per-point sums in fixed point
(normal_fixed.py) it is ``nx-sil-n6``, and an in-circuit solve takes the suffix ``-x``
(``lm-sil-ldlt-n6-x``).

The map-owner variant (suffix ``-mo``, e.g. ``lm-sil-ldlt-n6-mo``) takes the map points as
two XOR shares: ``world_masked`` from the device (xyz ^ P, the float32 bits under a pad)
and ``world_pad`` (P) from the map owner, its last input group, so the map owner's wires
are the last 96 n input wires. XOR is free, and the 6x6 solve stays inside: returning
J^T W J would show the device the geometry of the map points it never sees.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from snail_common.circuit import CircuitBuilder
from snail_common.circuit.ir import Circuit, Interface

from .do import ITERATIONS as DO_ITERATIONS
from .do import MAX_ITERATIONS as DO_MAX_ITERATIONS
from .do import OUTPUT_SHAPES as DO_OUTPUT_SHAPES
from .do import do_program
from .fops import CircuitBackend, F, MirrorBackend
from .sil import (
    ALGORITHMS,
    ARITHS,
    CLIENT,
    FIXED_OUTPUT_SHAPES,
    FIXED_OUTPUT_TYPES,
    INPUT_TYPES,
    NORMAL_OUTPUT_SHAPES,
    OUTPUT_SHAPES,
    SOLVERS,
    input_shapes,
    sil_program,
)

MODES = ("sil", "do")
MAX_POINTS = 4096
# Up to this many points the per-point division is depth-optimized too: +2.2 k AND per
# point buys ~500 fewer AND levels (~1,000 engine steps at ~10 us each), which pays off
# below ~50 points at ~10 M AND/s.
SHALLOW_POINTS = 32
ID_PATTERN = re.compile(r"^(?:(?P<algorithm>lm|gn)-(?P<mode>sil|do)-(?P<solver>ldlt|svd)"
                        r"-n(?P<points>[1-9][0-9]{0,3})(?:-i(?P<iterations>[1-9][0-9]?))?"
                        r"(?P<fixed>-x)?(?P<owner>-mo)?|n(?P<arith>[ex])-sil-n(?P<normal_points>[1-9][0-9]{0,3}))$")
MASKED = "world_masked"  # the device's share of the map points: float32 bits ^ pad
OWNER_PAD = "world_pad"  # the map owner's share: the pad, its last input group


@dataclass(frozen=True)
class Spec:
    """What a localization circuit computes; ``circuit_id`` is its public name.
    ``iterations`` is the DO circuit's fixed LM iteration count (named in the id with
    ``-iK`` when it is not the default)."""

    algorithm: str = "lm"
    mode: str = "sil"
    solver: str = "ldlt"
    points: int = 6
    iterations: int = DO_ITERATIONS
    owner: bool = False  # map points as device and map-owner shares (module doc)
    arith: str = "float"  # a SIL circuit's per-point arithmetic (normal_fixed.py)

    def __post_init__(self) -> None:
        if self.algorithm not in ALGORITHMS:
            raise ValueError(f"algorithm must be one of {ALGORITHMS}, got {self.algorithm!r}")
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {self.solver!r}")
        if self.mode == "do" and self.solver == CLIENT:
            raise ValueError("solver 'client' is for mode 'sil': the data-oblivious circuit "
                             "solves inside")
        if self.mode == "do" and self.algorithm != "lm":
            raise ValueError("mode 'do' is the data-oblivious LM baseline: algorithm must be lm")
        if not 4 <= self.points <= MAX_POINTS:
            raise ValueError(f"points must be in 4..{MAX_POINTS}, got {self.points}")
        if not 1 <= self.iterations <= DO_MAX_ITERATIONS:
            raise ValueError(f"iterations must be in 1..{DO_MAX_ITERATIONS}, "
                             f"got {self.iterations}")
        if self.mode == "sil" and self.iterations != DO_ITERATIONS:
            raise ValueError("iterations: a SIL circuit runs one iteration (only 'do' takes "
                             "an iteration count)")
        if self.arith not in ARITHS:
            raise ValueError(f"arith must be one of {ARITHS}, got {self.arith!r}")
        if self.arith == "fixed" and (self.mode != "sil" or self.solver == "svd"):
            raise ValueError("arith 'fixed' is for SIL circuits solved by the client or by "
                             "LDL^T")
        if self.owner and (self.mode != "sil" or self.solver == CLIENT):
            raise ValueError("the map-owner variant is a SIL circuit that solves inside "
                             "(the normal equations would reveal the map)")

    @property
    def circuit_id(self) -> str:
        if self.solver == CLIENT:
            return f"n{'x' if self.arith == 'fixed' else 'e'}-sil-n{self.points}"
        base = f"{self.algorithm}-{self.mode}-{self.solver}-n{self.points}"
        if self.iterations != DO_ITERATIONS:
            base = f"{base}-i{self.iterations}"
        return base + ("-x" if self.arith == "fixed" else "") + ("-mo" if self.owner else "")

    @property
    def registry_id(self) -> str:
        """The id servers know it by (``snail_common.circuit.registry``)."""
        return f"loc/{self.circuit_id}"

    @classmethod
    def parse(cls, circuit_id: str) -> Spec:
        match = ID_PATTERN.match(circuit_id)
        if not match:
            raise ValueError(f"not a localization circuit id: {circuit_id!r} "
                             f"(expected e.g. 'lm-sil-ldlt-n6')")
        if match["normal_points"]:
            return cls("lm", "sil", CLIENT, int(match["normal_points"]),
                       arith="fixed" if match["arith"] == "x" else "float")
        iterations = int(match["iterations"] or DO_ITERATIONS)
        return cls(match["algorithm"], match["mode"], match["solver"], int(match["points"]),
                   iterations, owner=bool(match["owner"]),
                   arith="fixed" if match["fixed"] else "float")


def build(spec: Spec) -> Circuit:
    """Emit the circuit of ``spec`` (seconds for hundreds of points; cache it)."""
    b = CircuitBuilder()
    be = CircuitBackend(b, depth_opt=spec.points <= SHALLOW_POINTS)
    inputs = {name: F(be, _input(b, spec, name, shape))
              for name, shape in input_shapes(spec.algorithm, spec.points,
                                              spec.solver, spec.arith).items()}
    if spec.owner:  # the shares meet in free XOR gates
        pad = b.input(OWNER_PAD, (spec.points, 3), bits=32, dtype="uint32")
        inputs["world"] = F(be, b.xor(inputs["world"].v, pad))
    outputs = program(spec, inputs)
    for name in output_shapes(spec):
        b.output(name, outputs[name].v, dtype=output_dtype(spec, name))
    return b.build()


def _input(b: CircuitBuilder, spec: Spec, name: str, shape: tuple[int, ...]) -> np.ndarray:
    """An input group's wires: float32 words, the device's masked share of the map, or
    an integer group of INPUT_TYPES."""
    if spec.owner and name == "world":
        return b.input(MASKED, shape, bits=32, dtype="uint32")
    dtype, bits = INPUT_TYPES.get(name, ("float32", 32))
    return b.input(name, shape, bits=bits, dtype=dtype)


def integer_outputs(spec: Spec) -> bool:
    """Whether the circuit returns fixed-point sums and their exponents (the client decodes
    them with normal_fixed.decode) rather than float32 values."""
    return spec.arith == "fixed" and spec.solver == CLIENT


def output_dtype(spec: Spec, name: str) -> str:
    """float32, but the fixed-point sums are integers and exponents."""
    return FIXED_OUTPUT_TYPES[name] if integer_outputs(spec) else "float32"


def output_shapes(spec: Spec) -> dict[str, tuple[int, ...]]:
    """SIL: the step and the cost (or the normal equations and the cost, for the client
    to solve); DO: the final pose and its cost."""
    if spec.mode == "do":
        return DO_OUTPUT_SHAPES
    if integer_outputs(spec):
        return FIXED_OUTPUT_SHAPES
    return NORMAL_OUTPUT_SHAPES if spec.solver == CLIENT else OUTPUT_SHAPES


def program(spec: Spec, inputs: dict[str, F]) -> dict[str, F]:
    if spec.mode == "do":
        return do_program(inputs, spec.solver, spec.iterations)
    return sil_program(inputs, spec.algorithm, spec.solver, spec.arith)


def owner_bits(circuit: Circuit | Interface) -> int:
    """How many of a circuit's input wires (the last ones) are the map owner's: the bits of
    a final ``world_pad`` group, else 0."""
    last = circuit.inputs[-1] if circuit.inputs else None
    return last.size if last is not None and last.name == OWNER_PAD else 0


def masked_wires(circuit: Circuit | Interface) -> slice:
    """The input wires (counted from the first input) of the device's ``world_masked``
    share in a map-owner circuit: where the device folds in the map owner's correction
    of a session's pad (snail_mapd/pads.py); an empty slice for another circuit."""
    start = 0
    for group in circuit.inputs if owner_bits(circuit) else ():
        if group.name == MASKED:
            return slice(start, start + group.size)
        start += group.size
    return slice(0, 0)


def run_mirror(spec: Spec, values: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The float32 mirror of the circuit: same inputs, bit-identical outputs."""
    be = MirrorBackend()
    if spec.owner:
        shares = np.asarray(values[MASKED], np.uint32) ^ np.asarray(values[OWNER_PAD],
                                                                     np.uint32)
        values = {**values, "world": shares.view(np.float32)}
    shapes = input_shapes(spec.algorithm, spec.points, spec.solver, spec.arith)
    missing = sorted(set(shapes) - set(values))
    if missing:
        raise ValueError(f"missing inputs {missing}")
    inputs = {name: F(be, np.asarray(values[name], np.int64 if name in INPUT_TYPES
                                     else np.float32).reshape(shape))
              for name, shape in shapes.items()}
    outputs = program(spec, inputs)
    return {name: np.asarray(outputs[name].v, output_dtype(spec, name))
            for name in output_shapes(spec)}
