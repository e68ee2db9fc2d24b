"""Compile an arith circuit once, run it on a whole batch of inputs in one evaluate call."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from snail_common.circuit import CircuitBuilder, evaluate, schedule_circuit


class Compiled:
    """A circuit of named inputs (name -> (bits, dtype)) and one output 'r'."""

    def __init__(self, fn: Callable, inputs: dict[str, tuple[int, str]], out_dtype: str):
        b = CircuitBuilder()
        wires = [b.input(name, (), bits, dtype) for name, (bits, dtype) in inputs.items()]
        out = np.asarray(fn(b, *wires))
        if out.ndim == 0:
            out = out[None]
        b.output("r", out, out_dtype)
        self.circuit = b.build()
        self.circuit.validate()
        self.schedule = schedule_circuit(self.circuit)
        self.names = list(inputs)
        self.dtypes = [dtype for _, dtype in inputs.values()]

    def __call__(self, *args) -> np.ndarray:
        arrays = [np.asarray(a).astype(dt) for a, dt in zip(args, self.dtypes)]
        n = len(arrays[0])
        return evaluate(self.circuit, dict(zip(self.names, arrays)), self.schedule,
                        batch=n)["r"]

    @property
    def ands(self) -> int:
        return self.circuit.counts()["and"]
