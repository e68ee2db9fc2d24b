"""Circuit IR: a topologically ordered netlist of XOR, AND and NOT gates in numpy arrays.

Wire numbering is implicit so a 50 M gate circuit stays a few flat arrays:
wire 0 is the constant 0, wire 1 the constant 1, wires 2 .. 2+n_inputs-1 the input bits,
and gate g drives wire ``2 + n_inputs + g``. A gate only reads wires with smaller ids,
so gate order is a topological order. NOT stores the constant-1 wire as its second
operand: it *is* XOR with 1, kept as its own kind for statistics and Bristol export.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field

import numpy as np

ZERO = 0
ONE = 1
FIRST_INPUT = 2

XOR = 0
AND = 1
NOT = 2
KIND_NAMES = {XOR: "XOR", AND: "AND", NOT: "NOT"}


@dataclass(frozen=True)
class Group:
    """A named, shaped block of words (e.g. ``points3d``: shape (n, 3), 32-bit float32).

    ``wires`` has shape ``shape + (bits,)``, least-significant bit first.
    ``dtype`` names how values are encoded: a numpy dtype name, ``"bool"``,
    or ``"int"`` for unbounded Python integers (Bristol words wider than 64 bits).
    """

    name: str
    shape: tuple[int, ...]
    bits: int
    dtype: str

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64)) * self.bits

    def to_json(self) -> dict:
        return {"name": self.name, "shape": list(self.shape), "bits": self.bits,
                "dtype": self.dtype}

    @staticmethod
    def from_json(d: dict) -> Group:
        return Group(d["name"], tuple(d["shape"]), int(d["bits"]), d["dtype"])


@dataclass
class Circuit:
    """A compiled netlist with named input and output groups.

    ``and_depth[g]`` is the AND-depth of gate g's output wire and ``xor_depth[g]`` its
    XOR-depth inside that AND layer; the scheduler groups gates by them.
    """

    n_inputs: int
    kind: np.ndarray  # uint8 (G,)
    a: np.ndarray  # int32 (G,)
    b: np.ndarray  # int32 (G,)
    outputs: np.ndarray  # int32 (n_outputs,) wire ids
    inputs: list[Group]
    output_groups: list[Group]
    and_depth: np.ndarray  # int32 (G,)
    xor_depth: np.ndarray  # int32 (G,)
    _hash: str | None = field(default=None, repr=False, compare=False)

    @property
    def n_gates(self) -> int:
        return len(self.kind)

    @property
    def n_wires(self) -> int:
        return FIRST_INPUT + self.n_inputs + self.n_gates

    @property
    def first_gate_wire(self) -> int:
        return FIRST_INPUT + self.n_inputs

    @property
    def n_outputs(self) -> int:
        return len(self.outputs)

    def counts(self) -> dict[str, int]:
        c = np.bincount(self.kind, minlength=3)
        return {"and": int(c[AND]), "xor": int(c[XOR]), "not": int(c[NOT])}

    def depth(self) -> int:
        """AND-depth of the whole circuit (0 for a purely linear one)."""
        return int(self.and_depth.max(initial=0))

    def input_offsets(self) -> dict[str, int]:
        """Offset of each input group in the flat input-bit vector."""
        return _offsets(self.inputs)

    def output_offsets(self) -> dict[str, int]:
        return _offsets(self.output_groups)

    def interface(self) -> Interface:
        """The part of the circuit a client needs (see ``Interface``)."""
        return Interface(self.n_inputs, tuple(self.inputs), tuple(self.output_groups),
                         self.content_hash(), self.counts(), self.depth())

    def content_hash(self) -> str:
        """SHA-256 over the netlist and its interface; identifies the circuit on the wire."""
        if self._hash is None:
            h = hashlib.sha256()
            meta = {"n_inputs": self.n_inputs,
                    "inputs": [g.to_json() for g in self.inputs],
                    "outputs": [g.to_json() for g in self.output_groups]}
            h.update(json.dumps(meta, sort_keys=True).encode())
            for arr, dt in ((self.kind, np.uint8), (self.a, np.int32), (self.b, np.int32),
                            (self.outputs, np.int32)):
                h.update(np.ascontiguousarray(arr, dtype=dt).tobytes())
            self._hash = h.hexdigest()
        return self._hash

    def validate(self) -> None:
        """Check the structural invariants; raises ValueError naming the first violation."""
        g = np.arange(self.n_gates, dtype=np.int64) + self.first_gate_wire
        for name, ops in (("a", self.a), ("b", self.b)):
            bad = np.flatnonzero((ops < 0) | (ops >= g))
            if bad.size:
                raise ValueError(f"gate {bad[0]} operand {name}={ops[bad[0]]} is not an "
                                 "earlier wire")
        if np.any(self.b[self.kind == NOT] != ONE):
            raise ValueError("NOT gates must use the constant-1 wire as operand b")
        if self.outputs.size and (self.outputs.min() < 0 or self.outputs.max() >= self.n_wires):
            raise ValueError("an output names a wire that does not exist")
        if sum(gr.size for gr in self.inputs) != self.n_inputs:
            raise ValueError("input groups do not cover the input bits exactly")
        if sum(gr.size for gr in self.output_groups) != self.n_outputs:
            raise ValueError("output groups do not cover the outputs exactly")


@dataclass(frozen=True)
class Interface:
    """What a client needs of a circuit: the input and output layout to encode and decode,
    the content hash to name it to the servers, and its size to report. A few hundred
    bytes, where the netlist and schedule of a large circuit are gigabytes."""

    n_inputs: int
    inputs: tuple[Group, ...]
    output_groups: tuple[Group, ...]
    content_hash: str
    counts: dict[str, int]
    depth: int

    @property
    def n_outputs(self) -> int:
        return sum(g.size for g in self.output_groups)

    def to_json(self) -> dict:
        return {"n_inputs": self.n_inputs, "inputs": [g.to_json() for g in self.inputs],
                "outputs": [g.to_json() for g in self.output_groups],
                "hash": self.content_hash, "counts": self.counts, "depth": self.depth}

    @staticmethod
    def from_json(d: dict) -> Interface:
        iface = Interface(int(d["n_inputs"]), tuple(Group.from_json(g) for g in d["inputs"]),
                          tuple(Group.from_json(g) for g in d["outputs"]), str(d["hash"]),
                          {k: int(v) for k, v in d["counts"].items()}, int(d["depth"]))
        if sum(g.size for g in iface.inputs) != iface.n_inputs:
            raise ValueError("interface input groups do not cover the input bits exactly")
        return iface


def _offsets(groups: list[Group]) -> dict[str, int]:
    out, pos = {}, 0
    for gr in groups:
        out[gr.name] = pos
        pos += gr.size
    return out


def compute_depths(n_inputs: int, kind: np.ndarray, a: np.ndarray,
                   b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """AND-depth and in-layer XOR-depth of every gate of a flat netlist (imported circuits).

    Builder circuits get these for free; this walks gates one by one, which is fine for
    the sizes of imported files (up to ~10^6 gates).
    """
    n_fixed = FIRST_INPUT + n_inputs
    depth = [0] * (n_fixed + len(kind))
    xdepth = [0] * (n_fixed + len(kind))
    for g, (k, x, y) in enumerate(zip(kind.tolist(), a.tolist(), b.tolist())):
        w = n_fixed + g
        dx, dy = depth[x], depth[y]
        if k == AND:
            depth[w] = max(dx, dy) + 1
        else:
            d = dx if dx > dy else dy
            depth[w] = d
            xdepth[w] = 1 + max(xdepth[x] if dx == d else 0, xdepth[y] if dy == d else 0)
    return (np.array(depth[n_fixed:], dtype=np.int32),
            np.array(xdepth[n_fixed:], dtype=np.int32))
