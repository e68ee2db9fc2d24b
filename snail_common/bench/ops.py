"""Gate counts of the float32 (and conversion) circuits, one scalar op each.

``ops_report()`` is what ``snail-bench ops --json`` prints: AND gates (the garbling
cost), XOR gates (free; NOT gates counted with them) and AND-depth per op.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from snail_common.arith import fadd, fcmp, fconvert, fdiv, fmul, fsqrt
from snail_common.circuit import CircuitBuilder

MUL_CONST = math.pi  # a constant with a full 24-bit significand


def _measure(fn: Callable, n_args: int, in_dtype: str = "float32",
             out_dtype: str = "float32") -> dict[str, int]:
    b = CircuitBuilder()
    args = [b.input(f"x{i}", (), 32, in_dtype) for i in range(n_args)]
    out = fn(b, *args)
    if out.ndim == 0:
        out = out[None]
        out_dtype = "bool"
    b.output("r", out, out_dtype)
    c = b.build()
    counts = c.counts()
    return {"and": counts["and"], "xor": counts["xor"] + counts["not"], "depth": c.depth()}


def op_builders() -> dict[str, tuple[Callable, int, str, str]]:
    """name -> (builder function, number of float32 inputs, input dtype, output dtype)."""
    f = "float32"
    return {
        "add": (fadd.fadd, 2, f, f),
        "add_depth_opt": (lambda b, x, y: fadd.fadd(b, x, y, depth_opt=True), 2, f, f),
        "sub": (fadd.fsub, 2, f, f),
        "sub_depth_opt": (lambda b, x, y: fadd.fsub(b, x, y, depth_opt=True), 2, f, f),
        "mul": (fmul.fmul, 2, f, f),
        "div": (fdiv.fdiv, 2, f, f),
        "div_depth_opt": (lambda b, x, y: fdiv.fdiv(b, x, y, depth_opt=True), 2, f, f),
        "sqrt": (fsqrt.fsqrt, 1, f, f),
        "sqrt_depth_opt": (lambda b, x: fsqrt.fsqrt(b, x, depth_opt=True), 1, f, f),
        "lt": (fcmp.lt, 2, f, "bool"),
        "lt_depth_opt": (lambda b, x, y: fcmp.lt(b, x, y, depth_opt=True), 2, f, "bool"),
        "le": (fcmp.le, 2, f, "bool"),
        "le_depth_opt": (lambda b, x, y: fcmp.le(b, x, y, depth_opt=True), 2, f, "bool"),
        "eq": (fcmp.eq, 2, f, "bool"),
        "min": (fcmp.fmin, 2, f, f),
        "max": (fcmp.fmax, 2, f, f),
        "i2f": (fconvert.i2f, 1, "int32", f),
        "f2i": (fconvert.f2i, 1, f, "int32"),
        "mul_const": (lambda b, x: fmul.fmul_const(b, x, MUL_CONST), 1, f, f),
    }


def ops_report() -> dict:
    """{"ops": {name: {"and": N, "xor": N, "depth": N}}} for every float32 op."""
    return {"ops": {name: _measure(fn, n, di, do)
                    for name, (fn, n, di, do) in op_builders().items()}}


if __name__ == "__main__":
    import json

    print(json.dumps(ops_report(), indent=1))
