"""Levelized schedule: the circuit as a short list of numpy-sized steps over reusable slots.

Two kinds of step alternate:
- AND step d: every AND gate of AND-depth d, as three slot arrays (out, a, b).
- linear step: XOR/NOT logic between AND layers, folded into multi-input XORs. Each
  materialized wire is the XOR of a list of *leaf* slots (CSR: ``ptr`` into ``terms``), so
  a whole XOR tree costs one gather + one ``bitwise_xor.reduceat`` and the schedule keeps
  about two steps per AND level however deep the XOR chains are.

A linear wire is materialized (gets a slot) only when something outside its own layer
needs it: an AND gate, a circuit output, or a linear gate of a later layer. Inside a
layer, XOR wires are expanded into their consumers. An expression longer than
``max_terms`` is cut: it is materialized in an extra sub-step and used as a leaf, which
bounds the duplicated work of shared XOR subtrees. Unused XOR logic disappears.

Slots are reused by liveness: a wire's slot returns to the free stack after the step of
its last read, and a step's outputs may take slots freed by that same step (executors
gather all operands before they scatter results). NOT is XOR with the constant-1 wire.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from .builder import _Growable
from .ir import AND, FIRST_INPUT, Circuit

LINEAR_STEP = 0
AND_STEP = 1
MAX_TERMS = 16
MAX_TERMS_SHARED = 4


class AndStep(NamedTuple):
    out: np.ndarray
    a: np.ndarray
    b: np.ndarray


class LinearStep(NamedTuple):
    """out[i] = XOR of slots terms[starts[i] : starts[i+1]].

    ``width`` is the common term count when every output has the same one (then
    ``terms.reshape(-1, width)`` is a dense matrix), else 0.
    """

    out: np.ndarray
    terms: np.ndarray
    starts: np.ndarray
    width: int


@dataclass
class Schedule:
    """Slot-level program shared by the cleartext evaluator, garbler and evaluator.

    Slots ``0 .. n_inputs+1`` hold the constants and input bits on entry.
    """

    n_inputs: int
    n_slots: int
    step_kind: np.ndarray  # uint8 (S,)
    step_lo: np.ndarray  # int64 (S,) first row in and_* (AND) or lin_out (LINEAR)
    step_hi: np.ndarray  # int64 (S,)
    and_out: np.ndarray
    and_a: np.ndarray
    and_b: np.ndarray
    lin_out: np.ndarray
    lin_ptr: np.ndarray  # int64 (M+1,) into lin_terms
    lin_terms: np.ndarray
    output_slots: np.ndarray
    _steps: list | None = field(default=None, repr=False, compare=False)

    ARRAYS = ("step_kind", "step_lo", "step_hi", "and_out", "and_a", "and_b", "lin_out",
              "lin_ptr", "lin_terms", "output_slots")

    @property
    def n_steps(self) -> int:
        return len(self.step_kind)

    @property
    def n_and(self) -> int:
        return len(self.and_out)

    def steps(self) -> list[AndStep | LinearStep]:
        """The steps as views, built once."""
        if self._steps is None:
            self._steps = [self._step(i) for i in range(self.n_steps)]
        return self._steps

    def _step(self, i: int) -> AndStep | LinearStep:
        lo, hi = int(self.step_lo[i]), int(self.step_hi[i])
        if self.step_kind[i] == AND_STEP:
            return AndStep(self.and_out[lo:hi], self.and_a[lo:hi], self.and_b[lo:hi])
        t0, t1 = int(self.lin_ptr[lo]), int(self.lin_ptr[hi])
        starts = self.lin_ptr[lo:hi] - t0
        counts = np.diff(self.lin_ptr[lo : hi + 1])
        width = int(counts[0]) if counts.size and np.all(counts == counts[0]) else 0
        return LinearStep(self.lin_out[lo:hi], self.lin_terms[t0:t1], starts, width)

    def to_arrays(self, prefix: str = "schedule_") -> dict[str, np.ndarray]:
        d = {prefix + k: getattr(self, k) for k in self.ARRAYS}
        d[prefix + "meta"] = np.array([self.n_inputs, self.n_slots], dtype=np.int64)
        return d

    @classmethod
    def from_arrays(cls, d, prefix: str = "schedule_") -> Schedule:
        n_inputs, n_slots = (int(v) for v in d[prefix + "meta"])
        return cls(n_inputs, n_slots, *(np.asarray(d[prefix + k]) for k in cls.ARRAYS))


def schedule_circuit(circuit: Circuit, reuse_slots: bool = True,
                     max_terms: int = MAX_TERMS) -> Schedule:
    """Compile a circuit into a Schedule (see the module docstring)."""
    plan = _fold(circuit, max_terms)
    slot_of, n_slots = _allocate_slots(circuit, plan, reuse_slots)
    return Schedule(
        n_inputs=circuit.n_inputs, n_slots=n_slots,
        step_kind=plan.kind, step_lo=plan.lo, step_hi=plan.hi,
        and_out=slot_of[plan.and_out], and_a=slot_of[plan.and_a], and_b=slot_of[plan.and_b],
        lin_out=slot_of[plan.lin_out], lin_ptr=plan.lin_ptr,
        lin_terms=slot_of[plan.lin_terms], output_slots=slot_of[circuit.outputs])


class _Plan(NamedTuple):
    """Steps over wire ids, before slot allocation."""

    kind: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    and_out: np.ndarray
    and_a: np.ndarray
    and_b: np.ndarray
    lin_out: np.ndarray
    lin_ptr: np.ndarray
    lin_terms: np.ndarray


def _groups(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stable sort order of keys and the [start, end) bounds of each run of equal keys."""
    order = np.argsort(keys, kind="stable").astype(np.int32)
    sk = keys[order]
    cuts = np.flatnonzero(sk[1:] != sk[:-1]) + 1
    del sk
    if not len(keys):
        return order, np.zeros(0, np.int64), np.zeros(0, np.int64)
    starts = np.concatenate([[0], cuts]).astype(np.int64)
    ends = np.concatenate([cuts, [len(keys)]]).astype(np.int64)
    return order, starts, ends


class _Folder:
    """Expands XOR logic layer by layer into leaf lists (see module docstring)."""

    def __init__(self, circuit: Circuit, max_terms: int) -> None:
        c = circuit
        self.c, self.max_terms = c, max_terms
        self.max_terms_shared = MAX_TERMS_SHARED
        self.F = c.first_gate_wire
        W = c.n_wires
        self.depth = np.zeros(W, np.int32)
        self.depth[self.F :] = c.and_depth
        self.linear = np.zeros(W, bool)
        self.linear[self.F :] = c.kind != AND
        # materialize: read by an AND gate, an output, or a linear gate of a later layer
        self.mat = np.zeros(W, bool)
        is_and = c.kind == AND
        self.mat[c.a[is_and]] = True
        self.mat[c.b[is_and]] = True
        self.mat[c.outputs] = True
        lin_g = np.flatnonzero(~is_and).astype(np.int32)
        lin_depth = c.and_depth[lin_g]
        for ops in (c.a, c.b):
            ops = ops[lin_g]
            self.mat[ops[self.depth[ops] < lin_depth]] = True
        self.mat &= self.linear
        self.cut = np.zeros(W, bool)
        self.estart = np.zeros(W, np.int32)
        self.elen = np.zeros(W, np.int32)
        self.need = np.zeros(W, np.int32)
        self.buf = _Growable(np.int32)

    def _piece(self, x: np.ndarray, d: int):
        same = self.linear[x] & (self.depth[x] == d)
        expand = same & ~self.cut[x]
        length = np.where(expand, self.elen[x], 1)
        need = np.where(expand, self.need[x], np.where(same, self.need[x] + 1, 0))
        return expand, length, need

    def add_gates(self, gates: np.ndarray, d: int) -> None:
        """Expression of each gate (all at the same AND- and XOR-depth) from its operands."""
        c, F = self.c, self.F
        xa, xb = c.a[gates], c.b[gates]
        ea, la, na = self._piece(xa, d)
        eb, lb, nb = self._piece(xb, d)
        out = gates + F
        glen = la + lb
        start = self.buf.n + np.cumsum(glen, dtype=np.int32) - glen
        leaves = np.stack([xa, xb], axis=1).ravel()
        if not (ea.any() or eb.any()):
            self.buf.extend(leaves)
        else:
            plen = np.stack([la, lb], axis=1).ravel()
            pexp = np.stack([ea, eb], axis=1).ravel()
            pstart = self.estart[leaves]
            piece = np.repeat(np.arange(plen.size, dtype=np.int32), plen)
            offs = np.arange(piece.size, dtype=np.int32) - np.repeat(np.cumsum(plen) - plen, plen)
            vals = leaves[piece]
            m = pexp[piece]
            vals[m] = self.buf.view[pstart[piece[m]] + offs[m]]
            self.buf.extend(vals)
        self.estart[out] = start
        self.elen[out] = glen
        self.need[out] = np.maximum(na, nb)
        big = (glen > self.max_terms) | (self.mat[out] & (glen > self.max_terms_shared))
        self.cut[out[big]] = True
        self.mat[out[big]] = True

    def flush(self, wires: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Materialized wires of the finished layer as (outs, terms, term counts), one
        entry per sub-step; resets the layer."""
        wires = wires[self.mat[wires]]
        out = []
        if wires.size:
            order, starts, ends = _groups(self.need[wires])
            wires = wires[order]
            lens = self.elen[wires]
            ends_t = np.cumsum(lens, dtype=np.int32)
            idx = np.repeat(self.estart[wires] - ends_t + lens, lens)
            idx += np.arange(idx.size, dtype=np.int32)
            terms = self.buf.view[idx]
            ptr = np.concatenate([[0], ends_t])
            for s, e in zip(starts, ends):
                out.append((wires[s:e], terms[ptr[s] : ptr[e]], lens[s:e]))
        self.buf.n = 0
        return out


def _fold(c: Circuit, max_terms: int) -> _Plan:
    F = c.first_gate_wire
    is_and = c.kind == AND
    and_g = np.flatnonzero(is_and).astype(np.int32)
    a_order, a_starts, a_ends = _groups(c.and_depth[and_g])
    and_g = and_g[a_order]
    del a_order
    and_depth_of_group = c.and_depth[and_g[a_starts]] if and_g.size else np.zeros(0, np.int32)

    lin_g = np.flatnonzero(~is_and).astype(np.int32)
    del is_and
    xmax = int(c.xor_depth.max(initial=0)) + 1
    key_type = np.int32 if (c.depth() + 1) * xmax < 2**31 else np.int64
    keys = c.and_depth[lin_g].astype(key_type) * xmax + c.xor_depth[lin_g]
    l_order, l_starts, l_ends = _groups(keys)
    del keys
    lin_g = lin_g[l_order]
    del l_order
    lin_layer = c.and_depth[lin_g[l_starts]] if lin_g.size else np.zeros(0, np.int32)

    folder = _Folder(c, max_terms)
    kinds, los, his = [], [], []
    and_rows = 0
    lin_outs, lin_terms, lin_lens = (_Growable(np.int32) for _ in range(3))
    lin_rows = 0
    gi = 0  # next linear group
    ai = 0  # next AND group
    for d in range(c.depth() + 1):
        first = gi
        while gi < len(l_starts) and lin_layer[gi] == d:
            folder.add_gates(lin_g[l_starts[gi] : l_ends[gi]], d)
            gi += 1
        if gi > first:
            layer_wires = lin_g[l_starts[first] : l_ends[gi - 1]] + F
            for outs, terms, lens in folder.flush(layer_wires):
                kinds.append(0)
                los.append(lin_rows)
                lin_rows += len(outs)
                his.append(lin_rows)
                lin_outs.extend(outs)
                lin_terms.extend(terms)
                lin_lens.extend(lens)
        if ai < len(a_starts) and and_depth_of_group[ai] == d + 1:
            n = int(a_ends[ai] - a_starts[ai])
            kinds.append(1)
            los.append(and_rows)
            and_rows += n
            his.append(and_rows)
            ai += 1

    del folder
    lin_ptr = np.zeros(lin_lens.n + 1, np.int64)
    np.cumsum(lin_lens.freeze(), out=lin_ptr[1:])
    return _Plan(
        kind=np.array(kinds, np.uint8), lo=np.array(los, np.int64), hi=np.array(his, np.int64),
        and_out=(and_g + F).astype(np.int32), and_a=c.a[and_g], and_b=c.b[and_g],
        lin_out=lin_outs.freeze(), lin_ptr=lin_ptr, lin_terms=lin_terms.freeze())


def _allocate_slots(c: Circuit, plan: _Plan, reuse: bool) -> tuple[np.ndarray, int]:
    """Map every scheduled wire to a slot; returns (slot_of over wire ids, n_slots)."""
    W, F = c.n_wires, FIRST_INPUT + c.n_inputs
    S = len(plan.kind)
    slot_of = np.full(W, -1, np.int32)
    slot_of[:F] = np.arange(F, dtype=np.int32)
    outs_of = [plan.and_out[plan.lo[s] : plan.hi[s]] if plan.kind[s] == AND_STEP
               else plan.lin_out[plan.lo[s] : plan.hi[s]] for s in range(S)]
    if not reuse:
        n_slots = F
        for outs in outs_of:
            slot_of[outs] = np.arange(n_slots, n_slots + outs.size, dtype=np.int32)
            n_slots += outs.size
        return slot_of, n_slots

    # Reverse scan: the first time a wire is met going backwards is its last read.
    seen = np.zeros(W, bool)
    seen[c.outputs] = True  # outputs are never freed
    marker = np.zeros(W, np.int32)
    freed_at: list[np.ndarray] = [np.zeros(0, np.int32)] * (S + 1)
    for s in range(S - 1, -1, -1):
        lo, hi = plan.lo[s], plan.hi[s]
        if plan.kind[s] == AND_STEP:
            reads = np.concatenate([plan.and_a[lo:hi], plan.and_b[lo:hi]])
        else:
            reads = plan.lin_terms[plan.lin_ptr[lo] : plan.lin_ptr[hi]]
        new = reads[~seen[reads]]
        marker[new] = np.arange(new.size, dtype=np.int32)  # keep one copy of each wire
        new = new[marker[new] == np.arange(new.size)]
        seen[new] = True
        freed_at[s] = new
    del marker
    # unread wires are freed one step after they are made (unread inputs: at step 0)
    freed_at[0] = np.concatenate([freed_at[0], np.flatnonzero(~seen[:F]).astype(np.int32)])

    stack = np.empty(W, np.int32)
    top = 0
    n_slots = F
    pending = np.zeros(0, np.int32)
    for s, outs in enumerate(outs_of):
        for freed in (pending, freed_at[s]):
            stack[top : top + freed.size] = slot_of[freed]
            top += freed.size
        freed_at[s] = pending = np.zeros(0, np.int32)
        k = outs.size
        take = min(k, top)
        slot_of[outs[:take]] = stack[top - take : top]
        top -= take
        slot_of[outs[take:]] = np.arange(n_slots, n_slots + k - take, dtype=np.int32)
        n_slots += k - take
        pending = outs[~seen[outs]]
    return slot_of, n_slots
