"""The single-iteration (SIL) program: cost and step at one pose, for LM or GN; or, with
solver ``client``, the cost and the normal equations, which the client damps and solves.

The ``client`` form is for the offload setting, where every input is the client's own:
the normal equations are a function of them, so returning them tells the client nothing
it could not compute, and it removes the sequential 6x6 solve (most of the AND depth at
small n) from the circuit; a rejected LM step is re-damped with no secure invocation.

Written once against fops.F, it is both the circuit (CircuitBackend) and its bit-identical
float32 mirror (MirrorBackend). Inputs and outputs are named exactly like the circuit's
groups (see INPUT_SHAPES).
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext

from .block_ldlt import SOLVE_FRAC, block_ldlt_solve
from .fixed import TC, fix_backend
from .fops import F, concat, stack
from .ldlt import ldlt_solve
from .normal import UPPER, normal_equations
from .normal_fixed import (
    H_SHIFT,
    H_SHIFT_SOLVE,
    W_MAP,
    W_R,
    W_RS,
    W_W,
    float_system,
    map_block,
    normal_equations_fixed,
    rotation_damping,
    with_floors,
)
from .svd import pinv_step, svd_solve, weighted_system

ALGORITHMS = ("lm", "gn")
CLIENT = "client"
SOLVERS = ("ldlt", "svd", CLIENT)
ARITHS = ("float", "fixed")  # a SIL circuit's per-point arithmetic (normal_fixed.py)
_DIAG = [UPPER.index((i, i)) for i in range(6)]


def takes_map_as_integers(solver: str, arith: str) -> bool:
    """Whether a SIL circuit's map input is the client's block fixed point (``wmap``,
    ``emap``: map_fixed) rather than float32 ``world``: only where the client solves (in
    the map-owner setting the map is not the client's to convert)."""
    return solver == CLIENT and arith == "fixed"


def input_shapes(algorithm: str, n: int, solver: str = "ldlt",
                 arith: str = "float") -> dict[str, tuple[int, ...]]:
    """Secret inputs of a SIL circuit, float32 unless INPUT_TYPES says otherwise: pose,
    damping (LM solved in the circuit only), normalized image points, centered map
    points, per-point per-axis weights, and for fixed arithmetic the same weights as
    integers (normal_fixed.py)."""
    shapes = {"R": (3, 3), "t": (3,)}
    if algorithm == "lm" and solver != CLIENT:
        shapes["lam"] = ()
    shapes["image"] = (n, 2)
    if takes_map_as_integers(solver, arith):
        shapes.update({"wmap": (n, 3), "emap": ()})
    else:
        shapes["world"] = (n, 3)
    shapes["weights"] = (n, 2)
    if arith == "fixed":
        shapes["wfix"] = (n, 2)
    return shapes


# the inputs that change between a frame's invocations; the rest are the frame's
ITERATION_INPUTS = ("R", "t", "lam")
# (dtype, bits) of the inputs that are not float32, and the fixed-point circuit's outputs
INPUT_TYPES = {"wfix": ("uint16", W_W), "wmap": ("uint32", W_MAP + 1), "emap": ("uint8", 8)}
FIXED_OUTPUT_TYPES = {"hess": "int64", "grad": "int64", "cost": "int64", "ec": "uint8",
                      "er": "uint8", "el": "uint8"}


OUTPUT_SHAPES = {"step": (6,), "cost": ()}
# J^T W J packed as normal.UPPER, J^T W r and the cost
NORMAL_OUTPUT_SHAPES = {"hess": (21,), "grad": (6,), "cost": ()}
# the same in fixed point, with the block exponents that scale them (normal_fixed.py)
FIXED_OUTPUT_SHAPES = {"hess": (21,), "grad": (6,), "cost": (), "ec": (), "er": (),
                       "el": (3,)}

Solver = Callable[[F, F], F]


def _solver(name: str, arith: str) -> Solver:
    """The named solver; LDL^T on the fixed-point sums is the block form (block_ldlt.py),
    whose cubic adjugates need the bounded entries float_system gives it."""
    if name == "ldlt":
        return block_ldlt_solve if arith == "fixed" else ldlt_solve
    if name == "svd":
        return svd_solve
    raise ValueError(f"solver must be one of {SOLVERS}, got {name!r}")


def damped(hess: F, lam: F, moved: F | None = None) -> F:
    """Fletcher's damping: every diagonal entry times (1 + lambda). With ``moved`` (the
    fixed-point family, whose step rotates about the map's origin: normal_fixed.py), the
    rotation entries are damped by their diagonal plus what the rotation moves the camera
    through the translation columns (normal_fixed.rotation_damping): the diagonal of the
    sums of a rotation about the camera, but for their cross terms. Damped by their own
    diagonal, a weak rotation (a tag seen head-on tilting) took steps that LM's x10 / /10
    could not tame: one of 1,000 one-tag scenes crawled to the cap in float64 too."""
    diag = hess[_DIAG]
    if moved is None:
        scaled = diag * (lam + 1.0)
    else:
        scaled = diag + concat([diag[0:3], diag[3:6] + moved]) * lam
    parts = [scaled[_DIAG.index(p)] if p in _DIAG else hess[p] for p in range(len(UPPER))]
    return stack(parts)


def sil_program(inputs: dict[str, F], algorithm: str, solver: str,
                arith: str = "float") -> dict[str, F | TC]:
    """One iteration: the step solving (H [+ lam diag H]) step = -g, and the cost, at the
    input pose."""
    if algorithm not in ALGORITHMS:
        raise ValueError(f"algorithm must be one of {ALGORITHMS}, got {algorithm!r}")
    if solver == CLIENT and arith == "fixed":
        hess, grad, cost, ec, er, el, _ = _fixed_sums(inputs, H_SHIFT, W_RS)
        return {"hess": hess, "grad": grad, "cost": cost,
                **{name: TC(e, 8) for name, e in (("ec", ec), ("er", er), ("el", el))}}
    if solver == CLIENT:
        hess, grad, cost = normal_equations(inputs["R"], inputs["t"], inputs["image"],
                                            inputs["world"], inputs["weights"])
        return {"hess": hess, "grad": grad, "cost": cost}
    if algorithm == "gn" and solver == "svd":  # the paper's GN: -pinv(J) r on the 2n x 6 J
        jac, res, cost = weighted_system(inputs["R"], inputs["t"], inputs["image"],
                                         inputs["world"], inputs["weights"])
        with cost.be.shallow():
            return {"step": pinv_step(jac, res), "cost": cost}
    unscale = blocks = None
    if arith == "fixed":
        hess, *sums = _fixed_sums(inputs, H_SHIFT_SOLVE)
        hess = with_floors(inputs["R"], hess, inputs["wfix"].v)
        hess, grad, cost, unscale = float_system(inputs["R"], hess, *sums)
        blocks = sums[-1], sums[-2]  # the map's exponent, the rotation columns' shifts
    else:
        hess, grad, cost = normal_equations(inputs["R"], inputs["t"], inputs["image"],
                                            inputs["world"], inputs["weights"])
    with hess.be.shallow():  # the solve is one long chain: spend gates to cut depth
        if algorithm == "lm":
            with _damping_precision(hess, arith):
                moved = None if blocks is None else rotation_damping(hess, inputs["t"], *blocks)
                hess = damped(hess, inputs["lam"], moved)
        step = _solver(solver, arith)(hess, -grad)
    return {"step": step if unscale is None else unscale(step), "cost": cost}


def _damping_precision(hess: F, arith: str) -> AbstractContextManager:
    """The block solve reads only SOLVE_FRAC fraction bits of the damped matrix: damping
    in that format costs one rounding there and shortens the chain by a float32 multiply."""
    return hess.be.narrow(SOLVE_FRAC) if arith == "fixed" else nullcontext()


def _fixed_sums(inputs: dict[str, F], h_shift: int = 0, r_bits: int = W_R) -> tuple:
    """normal_equations_fixed on the circuit's named inputs, and the map's block exponent
    (the rotation columns' scale): the map as the client's integers where it solves, else
    converted from its float32 input."""
    if "wmap" in inputs:
        fx = fix_backend(inputs["R"])
        block = fx.sign_magnitude(inputs["wmap"].v, W_MAP), inputs["emap"].v
    else:
        block = map_block(inputs["world"])
    return (*normal_equations_fixed(inputs["R"], inputs["t"], inputs["image"], block,
                                    inputs["weights"], inputs["wfix"].v, h_shift, r_bits),
            block[1])
