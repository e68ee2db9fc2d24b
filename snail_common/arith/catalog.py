"""The arithmetic ops by name, and the ``ops`` circuit family built from them.

``OPS`` is the one table of scalar ops: ``snail-bench ops`` measures every entry, the
garbled-op tests run every entry, and the ``ops`` family serves the float32 ones as
circuits of independent lanes (``ops/fmul-x64``: 64 multiplications).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable

from snail_common.circuit import CircuitBuilder, registry
from snail_common.circuit.ir import Circuit

from . import fadd, fcmp, fconvert, fdiv, fmul, fsqrt

MUL_CONST = math.pi  # a constant with a full 24-bit significand
F32 = "float32"

# name -> (builder of (b, *args), number of inputs, input dtype, output dtype)
OPS: dict[str, tuple[Callable, int, str, str]] = {
    "add": (fadd.fadd, 2, F32, F32),
    "add_depth_opt": (lambda b, x, y: fadd.fadd(b, x, y, depth_opt=True), 2, F32, F32),
    "sub": (fadd.fsub, 2, F32, F32),
    "sub_depth_opt": (lambda b, x, y: fadd.fsub(b, x, y, depth_opt=True), 2, F32, F32),
    "mul": (fmul.fmul, 2, F32, F32),
    "div": (fdiv.fdiv, 2, F32, F32),
    "div_depth_opt": (lambda b, x, y: fdiv.fdiv(b, x, y, depth_opt=True), 2, F32, F32),
    "sqrt": (fsqrt.fsqrt, 1, F32, F32),
    "sqrt_depth_opt": (lambda b, x: fsqrt.fsqrt(b, x, depth_opt=True), 1, F32, F32),
    "lt": (fcmp.lt, 2, F32, "bool"),
    "lt_depth_opt": (lambda b, x, y: fcmp.lt(b, x, y, depth_opt=True), 2, F32, "bool"),
    "le": (fcmp.le, 2, F32, "bool"),
    "le_depth_opt": (lambda b, x, y: fcmp.le(b, x, y, depth_opt=True), 2, F32, "bool"),
    "eq": (fcmp.eq, 2, F32, "bool"),
    "min": (fcmp.fmin, 2, F32, F32),
    "max": (fcmp.fmax, 2, F32, F32),
    "i2f": (fconvert.i2f, 1, "int32", F32),
    "f2i": (fconvert.f2i, 1, F32, "int32"),
    "mul_const": (lambda b, x: fmul.fmul_const(b, x, MUL_CONST), 1, F32, F32),
}

# the ops family: f<op> for the plain float32 ops, inputs x (and y), output z
SERVED = ("add", "sub", "mul", "div", "sqrt", "min", "max", "lt", "le", "eq")
MAX_COUNT = 4096
VERSION = "1"  # bump when an op's circuit changes (tests/test_circuit_keys.py checks)
_ID = re.compile(r"^f(?P<op>[a-z]+)-x(?P<count>[1-9][0-9]{0,3})$")


def build_ops(op: str, count: int) -> Circuit:
    """``count`` independent ``op``s: z[i] = op(x[i], y[i]) (``op`` a name in OPS)."""
    fn, arity, in_dtype, out_dtype = OPS[op]
    b = CircuitBuilder()
    args = [b.input(name, (count,), bits=32, dtype=in_dtype) for name in "xy"[:arity]]
    z = fn(b, *args)
    b.output("z", z[..., None] if out_dtype == "bool" else z, dtype=out_dtype)
    return b.build()


def _resolve(rest: str) -> Callable[[], Circuit]:
    m = _ID.match(rest)
    if not m:
        raise registry.UnknownCircuit("malformed ops circuit id")
    op, count = m["op"], int(m["count"])
    if op not in SERVED:
        raise registry.UnknownCircuit(f"unknown op 'f{op}' (known: "
                                      f"{', '.join('f' + name for name in SERVED)})")
    if count > MAX_COUNT:
        raise registry.UnknownCircuit(f"op count {count} exceeds {MAX_COUNT}")
    return lambda: build_ops(op, count)


FAMILY = registry.Family("ops", VERSION, _resolve, "ops/fmul-x64")
