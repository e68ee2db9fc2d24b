"""One float32 program, two executions: circuit gates or the numpy mirror.

Localization code is written once against ``F`` (a float32 array with operators). Run on a
``MirrorBackend`` it computes numpy float32 values; run on a ``CircuitBackend`` it emits
gates. Because both executions follow the same Python code, the operation order is the
same by construction, which is what makes the mirror bit-identical to the circuit.

Values index like numpy arrays over their *leading* axes only: a circuit value carries a
trailing 32-bit axis that generic code never sees, so code must use positive axes and no
Ellipsis.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence

import numpy as np

from snail_common.arith import fadd, fcmp, fconvert, fdiv, fmul, fsqrt
from snail_common.arith import mirror as m
from snail_common.arith.fbits import FRAC, check_frac
from snail_common.arith.fconst import fconst
from snail_common.circuit import CircuitBuilder

Scalar = float | int


class _Precision:
    """The fraction width of +, - and * (float32: 23): ``narrow(frac)`` switches them to a
    narrow format for a block of code; other ops stay float32, which narrow values are."""

    frac = FRAC

    @contextlib.contextmanager
    def narrow(self, frac: int) -> Iterator[None]:
        check_frac(frac)
        saved, self.frac = self.frac, frac
        try:
            yield
        finally:
            self.frac = saved


class MirrorBackend(_Precision):
    """numpy float32 with the circuits' flush-to-zero rules (snail_common.arith.mirror)."""

    @contextlib.contextmanager
    def shallow(self) -> Iterator[None]:
        """Same values either way: only the circuit's shape changes."""
        yield

    def and_gates(self) -> int:
        """Numbers cost no gates."""
        return 0

    def expect_and(self, total: int, why: str) -> None:
        """No gates, no limit."""

    def shape(self, v: np.ndarray) -> tuple[int, ...]:
        return np.shape(v)

    def const(self, value: float, shape: tuple[int, ...]) -> np.ndarray:
        return np.full(shape, np.float32(value), dtype=np.float32)

    def add(self, x, y):
        return m.add(x, y, self.frac)

    def sub(self, x, y):
        return m.sub(x, y, self.frac)

    def mul(self, x, y):
        return m.mul(x, y, self.frac)

    def round(self, x, frac: int):
        return m.fround(x, frac)

    def mul_const(self, x, c: float):
        return m.mul_const(x, c)

    def div(self, x, y):
        return m.div(x, y)

    def sqrt(self, x):
        return m.sqrt(x)

    def neg(self, x):
        return m.neg(x)

    def lt(self, x, y):
        return m.lt(x, y)

    def select(self, cond, if0, if1):
        return m.select(cond, if0, if1)

    def stack(self, vs: Sequence, axis: int):
        return np.stack([np.asarray(v, np.float32) for v in vs], axis=axis)

    def concat(self, vs: Sequence, axis: int):
        return np.concatenate([np.asarray(v, np.float32) for v in vs], axis=axis)


class CircuitBackend(_Precision):
    """Emits float32 circuits into ``builder``. ``depth_opt`` picks the shallow division and
    square root (more AND gates, far fewer AND levels); inside ``shallow()`` divisions,
    square roots and additions are all depth-optimized, for the sequential chain of the
    6x6 solve."""

    def __init__(self, builder: CircuitBuilder, depth_opt: bool = True) -> None:
        self.b = builder
        self.depth_opt = depth_opt
        self.in_shallow = False

    @contextlib.contextmanager
    def shallow(self) -> Iterator[None]:
        saved, self.in_shallow = self.in_shallow, True
        try:
            yield
        finally:
            self.in_shallow = saved

    def shape(self, v: np.ndarray) -> tuple[int, ...]:
        return np.shape(v)[:-1]

    def and_gates(self) -> int:
        """AND gates emitted so far."""
        return self.b.n_and

    def expect_and(self, total: int, why: str) -> None:
        """Refuse now if the program will emit ``total`` AND gates over the builder's limit."""
        self.b.expect_and(total, why)

    def const(self, value: float, shape: tuple[int, ...]) -> np.ndarray:
        return fconst(value, shape)

    def add(self, x, y):
        return fadd.fadd(self.b, x, y, depth_opt=self.in_shallow, frac=self.frac)

    def sub(self, x, y):
        return fadd.fsub(self.b, x, y, depth_opt=self.in_shallow, frac=self.frac)

    def mul(self, x, y):
        return fmul.fmul(self.b, x, y, frac=self.frac)

    def round(self, x, frac: int):
        return fconvert.fround(self.b, x, frac)

    def mul_const(self, x, c: float):
        return fmul.fmul_const(self.b, x, c)

    def div(self, x, y):
        return fdiv.fdiv(self.b, x, y, depth_opt=self.depth_opt or self.in_shallow)

    def sqrt(self, x):
        return fsqrt.fsqrt(self.b, x, depth_opt=self.depth_opt or self.in_shallow)

    def neg(self, x):
        return fcmp.fneg(self.b, x)

    def lt(self, x, y):
        return fcmp.lt(self.b, x, y)

    def select(self, cond, if0, if1):
        return fcmp.fselect(self.b, cond, if0, if1)

    def stack(self, vs: Sequence, axis: int):
        return np.stack([np.asarray(v) for v in vs], axis=axis)

    def concat(self, vs: Sequence, axis: int):
        return np.concatenate([np.asarray(v) for v in vs], axis=axis)


Backend = MirrorBackend | CircuitBackend


class F:
    """A float32 array on a backend, with +, -, *, / and leading-axis indexing.

    A Python number on the other side of an operator is a public constant: ``x * 2.0``
    uses the cheaper constant multiplier, ``x + 1.0`` adds a constant word.
    """

    __slots__ = ("be", "v")

    def __init__(self, be: Backend, v) -> None:
        self.be = be
        self.v = v

    @property
    def shape(self) -> tuple[int, ...]:
        return self.be.shape(self.v)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, idx) -> F:
        if idx is Ellipsis or (isinstance(idx, tuple) and any(i is Ellipsis for i in idx)):
            raise IndexError("F values index leading axes only (no Ellipsis)")
        return F(self.be, self.v[idx])

    def _lift(self, other) -> F:
        if isinstance(other, F):
            return other
        return F(self.be, self.be.const(float(other), ()))

    def __add__(self, other) -> F:
        return F(self.be, self.be.add(self.v, self._lift(other).v))

    def __radd__(self, other) -> F:
        return F(self.be, self.be.add(self._lift(other).v, self.v))

    def __sub__(self, other) -> F:
        return F(self.be, self.be.sub(self.v, self._lift(other).v))

    def __rsub__(self, other) -> F:
        return F(self.be, self.be.sub(self._lift(other).v, self.v))

    def __mul__(self, other) -> F:
        if isinstance(other, F):
            return F(self.be, self.be.mul(self.v, other.v))
        return F(self.be, self.be.mul_const(self.v, float(other)))

    def __rmul__(self, other) -> F:
        return self.__mul__(other)

    def __truediv__(self, other) -> F:
        return F(self.be, self.be.div(self.v, self._lift(other).v))

    def __rtruediv__(self, other) -> F:
        return F(self.be, self.be.div(self._lift(other).v, self.v))

    def __neg__(self) -> F:
        return F(self.be, self.be.neg(self.v))

    def sqrt(self) -> F:
        return F(self.be, self.be.sqrt(self.v))

    def round(self, frac: int) -> F:
        """Rounded to nearest even with ``frac`` fraction bits (still a float32 value)."""
        return F(self.be, self.be.round(self.v, frac))

    def lt(self, other) -> Cond:
        return Cond(self.be, self.be.lt(self.v, self._lift(other).v))

    def sum(self, axis: int = 0) -> F:
        """Pairwise (tree) sum along ``axis``: log-depth, and a fixed order both backends share."""
        x = self
        while x.shape[axis] > 1:
            size = x.shape[axis]
            half = size // 2
            head = (slice(None),) * axis
            pairs = x[(*head, slice(0, 2 * half, 2))] + x[(*head, slice(1, 2 * half, 2))]
            x = pairs if size % 2 == 0 else concat([pairs, x[(*head, slice(size - 1, size))]], axis)
        return x[(slice(None),) * axis + (0,)]


class Cond:
    """A boolean array on a backend (one wire per element in a circuit)."""

    __slots__ = ("be", "v")

    def __init__(self, be: Backend, v) -> None:
        self.be = be
        self.v = v

    def select(self, if_false: F, if_true: F) -> F:
        return F(self.be, self.be.select(self.v, if_false.v, if_true.v))


def stack(values: Sequence[F], axis: int = 0) -> F:
    be = values[0].be
    return F(be, be.stack([x.v for x in values], axis))


def concat(values: Sequence[F], axis: int = 0) -> F:
    be = values[0].be
    return F(be, be.concat([x.v for x in values], axis))


def const(be: Backend, value: float, shape: tuple[int, ...] = ()) -> F:
    return F(be, be.const(value, shape))
