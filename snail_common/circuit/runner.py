"""The one schedule runner: walks a plan over a slot array with a pluggable AND kernel.

Cleartext evaluation, garbling and evaluation differ only in what an AND gate does (a
bitwise AND of packed bits; a half-gates garbling that writes tables; an evaluation
that reads them), so all three are this loop with a different kernel. Linear steps are
XORs of rows, the same for bits and labels.

The runner is a generator: before every block of AND gates it yields the block's gate
count and receives the block's tables (or None) by ``send``, which lets a garbler flush
a full frame first, and an evaluator wait, suspended, until the block's tables have
arrived. A caller that has no tables just drives it with ``drain``.
"""

from __future__ import annotations

from collections.abc import Generator
from typing import Protocol

import numpy as np

from .plan import AndOutputs, AndPlan, Plan, Scratch
from .slots import Rows, part, slot_view


class AndKernel(Protocol):
    def __call__(self, values: np.ndarray, a: Rows, b: Rows, gate0: int, out: np.ndarray,
                 tables: np.ndarray | None) -> None:
        """Compute AND gates gate0 .. gate0+len(out)-1 of operand rows ``a`` and ``b`` of
        ``values`` into ``out`` (which may alias rows of ``values``: read every operand
        before writing), reading or writing the block's ``tables``."""


Run = Generator[int, "np.ndarray | None", None]


def run_plan(plan: Plan, values: np.ndarray, kernel: AndKernel, block: int) -> Run:
    """Run every step of ``plan`` on ``values`` (n_slots, W) in place, AND gates in blocks
    of at most ``block``; see the module docstring for the yield/send protocol."""
    slots = slot_view(values)
    scratch = Scratch(values.shape[1])
    outputs = AndOutputs(values, slots, block)
    for step in plan.steps:
        if not isinstance(step, AndPlan):
            step.run(values, slots, scratch)
            continue
        if step.n <= block:  # the common case: the whole piece is one block
            tables = yield step.n
            kernel(values, step.a, step.b, step.first, outputs.target(step, 0, step.n), tables)
            outputs.store(step, 0, step.n)
            continue
        for k in range(0, step.n, block):
            m = min(block, step.n - k)
            tables = yield m
            kernel(values, part(step.a, k, m), part(step.b, k, m), step.first + k,
                   outputs.target(step, k, m), tables)
            outputs.store(step, k, m)


def first_block(run: Run) -> int | None:
    """Start ``run``: the gate count of its first AND block, or None if it has none."""
    return next(run, None)


def next_block(run: Run, tables: np.ndarray | None) -> int | None:
    """Run the pending block with ``tables``: the next block's gate count, or None once
    the run has ended."""
    try:
        return run.send(tables)
    except StopIteration:
        return None


def drain(run: Run) -> None:
    """Drive a run that needs no tables to its end."""
    for _ in run:
        pass
