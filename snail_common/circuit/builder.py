"""Vectorized circuit builder: every call takes arrays of wire ids and emits a whole batch.

Operands broadcast like numpy arrays, so ``b.xor(x, y)`` on two (n, 32) word arrays
emits 32n gates in one call. Constants and equal operands are folded on the way
(``x & 0 -> 0``, ``x ^ x -> 0``, ``x & 1 -> x`` ...), so arithmetic written against
public constants costs only the gates it really needs. Each new wire's AND-depth and
XOR-depth are computed here, batch by batch, so scheduling never walks gates one by one.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from contextvars import ContextVar

import numpy as np

from .ir import AND, FIRST_INPUT, NOT, ONE, XOR, ZERO, Circuit, Group

WireArray = np.ndarray

# AND gates a builder may emit (None: no limit); set per thread by ``and_gate_limit``
_and_limit: ContextVar[int | None] = ContextVar("and_limit", default=None)


class CircuitTooLarge(ValueError):
    """A circuit being built crossed the AND-gate limit in force."""


@contextlib.contextmanager
def and_gate_limit(limit: int | None) -> Iterator[None]:
    """Builders created inside stop with CircuitTooLarge once they emit more than
    ``limit`` AND gates: a server bounds the time and memory one request may make it
    spend on compiling, without knowing the circuit's size in advance."""
    token = _and_limit.set(limit)
    try:
        yield
    finally:
        _and_limit.reset(token)



class _Growable:
    """Append-only numpy array with amortized doubling.

    Grows and shrinks with ``ndarray.resize`` (realloc, which moves large blocks by
    remapping pages), so a 50 M-entry array never exists twice. Any ``view`` taken before
    an ``extend`` is invalid afterwards: read what you need first. ``growth`` below 2
    trades more (cheap) reallocations for less unused capacity at the peak.
    """

    def __init__(self, dtype, capacity: int = 1 << 12, growth: float = 2.0) -> None:
        self._buf = np.empty(capacity, dtype=dtype)
        self.n = 0
        self.growth = growth

    def extend(self, values: np.ndarray) -> None:
        k = values.size
        if self.n + k > self._buf.size:
            self._buf.resize(max(int(self.growth * self._buf.size), self.n + k), refcheck=False)
        self._buf[self.n : self.n + k] = values.ravel()
        self.n += k

    @property
    def view(self) -> np.ndarray:
        return self._buf[: self.n]

    def freeze(self) -> np.ndarray:
        """The contents, trimmed in place; the builder is empty afterwards."""
        out = self._buf
        out.resize(self.n, refcheck=False)
        self._buf = np.empty(0, dtype=out.dtype)
        self.n = 0
        return out


class CircuitBuilder:
    """Builds a Circuit. Declare every input before emitting the first gate."""

    def __init__(self) -> None:
        self._inputs: list[Group] = []
        self._n_inputs = 0
        self._kind = _Growable(np.uint8)
        self._a = _Growable(np.int32)
        self._b = _Growable(np.int32)
        # per wire: AND-depth and XOR-depth within its AND layer (constants/inputs: 0)
        self._depth = _Growable(np.int32)
        self._xdepth = _Growable(np.int32)
        self._depth.extend(np.zeros(FIRST_INPUT, np.int32))
        self._xdepth.extend(np.zeros(FIRST_INPUT, np.int32))
        self._outputs: list[tuple[Group, np.ndarray]] = []
        self._n_and = 0
        self._max_and = _and_limit.get()

    # ---- interface -------------------------------------------------------------------
    def input(self, name: str, shape: Sequence[int] | int = (), bits: int = 1,
              dtype: str | None = None) -> WireArray:
        """Declare an input group; returns wire ids of shape ``shape + (bits,)``."""
        if self._kind.n:
            raise RuntimeError(f"input {name!r} declared after gates were emitted")
        if any(g.name == name for g in self._inputs):
            raise ValueError(f"duplicate input name {name!r}")
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        group = Group(name, shape, bits, dtype or _default_dtype(bits))
        start = FIRST_INPUT + self._n_inputs
        wires = np.arange(start, start + group.size, dtype=np.int32)
        self._inputs.append(group)
        self._n_inputs += group.size
        self._depth.extend(np.zeros(group.size, np.int32))
        self._xdepth.extend(np.zeros(group.size, np.int32))
        return wires.reshape(shape + (bits,))

    def output(self, name: str, wires: WireArray, dtype: str | None = None) -> None:
        """Declare an output group; the last axis of ``wires`` is the bit axis (LSB first)."""
        wires = np.asarray(wires, dtype=np.int32)
        if wires.ndim == 0:
            wires = wires.reshape(1)
        if any(g.name == name for g, _ in self._outputs):
            raise ValueError(f"duplicate output name {name!r}")
        bits = wires.shape[-1]
        self._outputs.append((Group(name, wires.shape[:-1], bits,
                                    dtype or _default_dtype(bits)), wires.ravel()))

    def build(self) -> Circuit:
        outputs = (np.concatenate([w for _, w in self._outputs]) if self._outputs
                   else np.zeros(0, np.int32))
        n_fixed = FIRST_INPUT + self._n_inputs
        depth = self._depth.freeze()[n_fixed:]
        xdepth = self._xdepth.freeze()[n_fixed:]
        return Circuit(self._n_inputs, self._kind.freeze(), self._a.freeze(), self._b.freeze(),
                       outputs.astype(np.int32), list(self._inputs),
                       [g for g, _ in self._outputs], depth, xdepth)

    @property
    def n_gates(self) -> int:
        return self._kind.n

    @property
    def n_and(self) -> int:
        return self._n_and

    def expect_and(self, total: int, why: str) -> None:
        """Stop now with CircuitTooLarge if the finished circuit will have ``total`` AND
        gates, over the limit in force: a program that repeats a block can refuse after
        building one repetition rather than after as many as fit under the limit."""
        if self._over_limit(total):
            raise CircuitTooLarge(f"{why}: about {total:,} AND gates, more than "
                                  f"{self._max_and:,}")

    def _over_limit(self, n_and: int) -> bool:
        return self._max_and is not None and n_and > self._max_and

    # ---- gates -----------------------------------------------------------------------
    @staticmethod
    def const(bit: int | np.ndarray) -> WireArray:
        """Wire ids of public constant bits (0 -> wire 0, 1 -> wire 1)."""
        return np.where(np.asarray(bit) != 0, ONE, ZERO).astype(np.int32)

    def const_word(self, value: int, bits: int) -> WireArray:
        """Wire ids of the constant ``value`` as ``bits`` bits, LSB first."""
        return self.const([(value >> i) & 1 for i in range(bits)])

    def xor(self, x: WireArray, y: WireArray) -> WireArray:
        x, y = _pair(x, y)
        out = np.empty(x.shape, np.int32)
        simple = (x > ONE) & (y > ONE) & (x != y)
        if simple.all():
            return self._emit(XOR, x, y)
        out[x == y] = ZERO
        m = (x == ZERO) & (y != ZERO)
        out[m] = y[m]
        m = (y == ZERO) & (x != ZERO)
        out[m] = x[m]
        m = (x == ONE) & (y > ONE)
        out[m] = self._emit(NOT, y[m], np.full(int(m.sum()), ONE, np.int32))
        m = (y == ONE) & (x > ONE)
        out[m] = self._emit(NOT, x[m], np.full(int(m.sum()), ONE, np.int32))
        out[simple] = self._emit(XOR, x[simple], y[simple])
        return out

    def and_(self, x: WireArray, y: WireArray) -> WireArray:
        x, y = _pair(x, y)
        simple = (x > ONE) & (y > ONE) & (x != y)
        if simple.all():
            return self._emit(AND, x, y)
        out = np.empty(x.shape, np.int32)
        out[(x == ZERO) | (y == ZERO)] = ZERO
        m = (x == ONE) & (y != ZERO)
        out[m] = y[m]
        m = (y == ONE) & (x != ZERO)
        out[m] = x[m]
        m = (x == y) & (x > ONE)
        out[m] = x[m]
        out[simple] = self._emit(AND, x[simple], y[simple])
        return out

    def not_(self, x: WireArray) -> WireArray:
        return self.xor(x, ONE)

    def or_(self, x: WireArray, y: WireArray) -> WireArray:
        """x | y = x ^ y ^ (x & y): one AND gate."""
        return self.xor(self.xor(x, y), self.and_(x, y))

    def mux(self, sel: WireArray, if0: WireArray, if1: WireArray) -> WireArray:
        """``if1`` where sel is 1 else ``if0``: one AND gate per bit."""
        return self.xor(if0, self.and_(sel, self.xor(if0, if1)))

    def _emit(self, kind: int, x: np.ndarray, y: np.ndarray) -> WireArray:
        """Append gates of one kind; returns their output wires in the shape of x."""
        n = x.size
        start = FIRST_INPUT + self._n_inputs + self._kind.n
        if n == 0:
            return np.zeros(x.shape, np.int32)
        xf, yf = x.ravel(), y.ravel()
        depth = self._depth.view
        xdepth = self._xdepth.view
        dx, dy = depth[xf], depth[yf]
        if kind == AND:
            if self._over_limit(self._n_and + n):  # refused batches are not counted
                raise CircuitTooLarge(f"the circuit needs more than {self._max_and:,} "
                                      "AND gates")
            self._n_and += n
            d = np.maximum(dx, dy) + 1
            xd = np.zeros(n, np.int32)
        else:
            d = np.maximum(dx, dy)
            xd = 1 + np.maximum(np.where(dx == d, xdepth[xf], 0), np.where(dy == d, xdepth[yf], 0))
        self._kind.extend(np.full(n, kind, np.uint8))
        self._a.extend(xf)
        self._b.extend(yf)
        self._depth.extend(d)
        self._xdepth.extend(xd)
        return np.arange(start, start + n, dtype=np.int32).reshape(x.shape)


def _pair(x: WireArray, y: WireArray) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.broadcast_arrays(np.asarray(x, dtype=np.int32), np.asarray(y, dtype=np.int32))
    return x, y


def _default_dtype(bits: int) -> str:
    if bits == 1:
        return "bool"
    if bits in (8, 16, 32, 64):
        return f"uint{bits}"
    return "int"
