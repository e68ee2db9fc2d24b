"""Gate counts of the float32 (and conversion) circuits, one scalar op each.

``ops_report()`` is what ``snail-bench ops --json`` prints: AND gates (the garbling
cost), XOR gates (free; NOT gates counted with them) and AND-depth per op.
"""

from __future__ import annotations

from collections.abc import Callable

from snail_common.arith.catalog import OPS
from snail_common.circuit import CircuitBuilder


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


def ops_report() -> dict:
    """{"ops": {name: {"and": N, "xor": N, "depth": N}}} for every op of the catalogue."""
    return {"ops": {name: _measure(fn, n, di, do) for name, (fn, n, di, do) in OPS.items()}}


if __name__ == "__main__":
    import json

    print(json.dumps(ops_report(), indent=1))
