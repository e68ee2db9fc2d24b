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

Slots are reused by liveness and laid out for locality (random gathers over a slot array
larger than the cache cost ~10 ns each). Walking steps backwards, each step's rows are
ordered (linear steps: by term count first) so that wires dying at the same step sit
together, in the order their last reader reads them; each such run gets one contiguous
block of slots, best fit among the blocks freed before the step (never a slot the step
itself reads, so executors may write outputs as they go). Wide, regular circuits then
read and write long runs of equally spaced slots, which executors can process as strided
views instead of gathers. Best fit wastes next to nothing (the compiler benchmark needs
its live width plus 2 slots); not reusing a step's own reads costs their count at the
peak step (there: every input is read last by the first AND step, 10.2 M slots instead
of 9.1 M). NOT is XOR with the constant-1 wire.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import pairwise
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

    Slots ``0 .. n_inputs+1`` hold the constants and input bits on entry. Executors gather
    a step's operands before writing its outputs, unless ``disjoint_io`` says no step
    writes a slot that it reads (true for every schedule ``schedule_circuit`` makes).
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
    disjoint_io: bool = False
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
        d[prefix + "meta"] = np.array([self.n_inputs, self.n_slots, self.disjoint_io],
                                      dtype=np.int64)
        return d

    @classmethod
    def from_arrays(cls, d, prefix: str = "schedule_") -> Schedule:
        meta = [int(v) for v in d[prefix + "meta"]]  # older files lack disjoint_io
        return cls(meta[0], meta[1], *(np.asarray(d[prefix + k]) for k in cls.ARRAYS),
                   disjoint_io=len(meta) > 2 and bool(meta[2]))


def schedule_circuit(circuit: Circuit, reuse_slots: bool = True,
                     max_terms: int = MAX_TERMS) -> Schedule:
    """Compile a circuit into a Schedule (see the module docstring)."""
    plan = _fold(circuit, max_terms)
    death = _order_rows(circuit, plan)
    slot_of, n_slots = _allocate_slots(circuit, plan, death, reuse_slots)
    del death
    for arr in (plan.and_out, plan.and_a, plan.and_b, plan.lin_out, plan.lin_terms):
        _to_slots(slot_of, arr)
    output_slots = slot_of[circuit.outputs]
    del slot_of  # before lin_ptr, 8 bytes a row: the two are the peak otherwise
    lin_ptr = np.zeros(plan.lin_lens.size + 1, np.int64)
    np.cumsum(plan.lin_lens, dtype=np.int64, out=lin_ptr[1:])
    return Schedule(
        n_inputs=circuit.n_inputs, n_slots=n_slots,
        step_kind=plan.kind, step_lo=plan.lo, step_hi=plan.hi,
        and_out=plan.and_out, and_a=plan.and_a, and_b=plan.and_b, lin_out=plan.lin_out,
        lin_ptr=lin_ptr, lin_terms=plan.lin_terms, output_slots=output_slots,
        disjoint_io=True)


class _Plan(NamedTuple):
    """Steps over wire ids, before slot allocation."""

    kind: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    and_out: np.ndarray
    and_a: np.ndarray
    and_b: np.ndarray
    lin_out: np.ndarray
    lin_lens: np.ndarray  # uint8 (M,) term count of each row (lin_ptr is 8 bytes a row)
    lin_terms: np.ndarray
    term_lo: np.ndarray  # int64 (S,) first term of each linear step

    def terms_of(self, s: int) -> np.ndarray:
        """The terms of linear step s, row after row (a view)."""
        t0 = int(self.term_lo[s])
        n = int(self.lin_lens[self.lo[s] : self.hi[s]].sum(dtype=np.int64))
        return self.lin_terms[t0 : t0 + n]


def _groups(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stable sort order of keys and the [start, end) bounds of each run of equal keys."""
    small = keys.size and keys.min() >= 0 and keys.max() < 2**16
    sort_keys = keys.astype(np.uint16) if small else keys  # 16-bit keys get a radix sort
    order = np.argsort(sort_keys, kind="stable").astype(np.int32)
    del sort_keys
    sk = keys[order]
    cuts = np.flatnonzero(sk[1:] != sk[:-1]) + 1
    del sk
    if not len(keys):
        return order, np.zeros(0, np.int64), np.zeros(0, np.int64)
    starts = np.concatenate([[0], cuts]).astype(np.int64)
    ends = np.concatenate([cuts, [len(keys)]]).astype(np.int64)
    return order, starts, ends


def _narrow(limit: int) -> type:
    """The narrowest signed integer type holding -1 .. limit."""
    return np.int16 if limit < 2**15 else np.int32


def _depth_order(c: Circuit) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gates sorted stably by (linear, AND-depth) in one pass, a radix sort when the keys
    fit 16 bits: the AND gates by depth, then the linear gates by layer.

    Returns (order, and_ptr, lin_ptr): the AND gates of depth d are
    ``order[and_ptr[d] : and_ptr[d + 1]]``, the linear gates of layer d
    ``order[lin_ptr[d] : lin_ptr[d + 1]]``.
    """
    D = c.depth() + 1
    keys = c.and_depth.astype(np.uint16 if 2 * D <= 2**16 else np.int32)
    keys[c.kind != AND] += D
    order = np.argsort(keys, kind="stable").astype(np.int32)
    ptr = np.zeros(2 * D + 1, np.int64)
    np.cumsum(np.bincount(keys, minlength=2 * D), out=ptr[1:])
    return order, ptr[: D + 1], ptr[D:]


def _materialized(c: Circuit, chunk: int = 1 << 22) -> np.ndarray:
    """Per wire: is it a linear wire read outside its own layer (by an AND gate, an output
    or a linear gate of a later layer), so it needs a slot? Walks the gates in chunks so
    no temporary is circuit-sized."""
    F = c.first_gate_wire
    is_and = c.kind == AND
    layer = np.full(c.n_wires, -1, _narrow(c.depth() + 1))  # AND-depth of linear wires
    layer[F:] = c.and_depth
    layer[F:][is_and] = -1
    mat = np.zeros(c.n_wires, bool)
    for g0 in range(0, c.n_gates, chunk):
        # an AND gate reads every linear wire from outside, a linear gate earlier layers'
        reader = np.where(is_and[g0 : g0 + chunk], np.iinfo(layer.dtype).max,
                          c.and_depth[g0 : g0 + chunk])
        for ops in (c.a[g0 : g0 + chunk], c.b[g0 : g0 + chunk]):
            mat[ops[layer[ops] < reader]] = True
    mat[c.outputs] = True
    mat &= layer >= 0
    return mat


class _Folder:
    """Expands XOR logic layer by layer into leaf lists (see module docstring).

    ``info[w]`` says how the current layer's gates read wire w: its term count in the low
    byte and its sub-step need above. Wires of other layers read as leaves (1, 0) and cut
    wires as leaves one sub-step later (1, need + 1), so one gather per operand decides
    whether to expand it, how long it is and when it is ready.
    """

    def __init__(self, c: Circuit, max_terms: int) -> None:
        if not 2 <= max_terms <= 127:
            raise ValueError(f"max_terms must be in 2..127, got {max_terms}")
        self.c, self.F = c, c.first_gate_wire
        self.max_terms, self.max_terms_shared = max_terms, MAX_TERMS_SHARED
        self.mat = _materialized(c)
        # need <= XOR-depth + 1 must fit the bits above the term count (<= 2 * max_terms)
        info_type = np.uint16 if c.xor_depth.max(initial=0) < 2**8 - 1 else np.uint32
        self.info = np.ones(c.n_wires, info_type)
        self.elen = np.zeros(c.n_wires, np.uint8)
        self.estart = np.zeros(c.n_wires, np.int32)
        self.buf = _Growable(np.int32)

    def add_gates(self, gates: np.ndarray) -> None:
        """Expression of each gate (all of one layer and XOR-depth) from its operands.

        The operands are pieces of length ``plen``: expanded wires copy their expression,
        leaves themselves. Appending the leaves to the buffer for a moment lets one gather
        copy every piece."""
        c, buf = self.c, self.buf
        leaves = np.stack([c.a[gates], c.b[gates]], axis=1).ravel()
        info = self.info[leaves]
        plen = (info & 0xFF).astype(np.int32)
        ends = np.cumsum(plen, dtype=np.int32)
        glen = plen[0::2] + plen[1::2]
        need = np.maximum(info[0::2] >> 8, info[1::2] >> 8)
        start = buf.n + ends[1::2] - glen
        expand = plen > 1
        if expand.any():
            base = np.arange(buf.n, buf.n + leaves.size, dtype=np.int32)
            buf.extend(leaves)
            base[expand] = self.estart[leaves[expand]]
            src = np.repeat(base - ends + plen, plen)
            src += np.arange(src.size, dtype=np.int32)
            vals = buf.view[src]
            buf.n -= leaves.size
            buf.extend(vals)
        else:
            buf.extend(leaves)
        out = gates + self.F
        self.estart[out] = start
        self.elen[out] = glen
        big = glen > self.max_terms
        big |= self.mat[out] & (glen > self.max_terms_shared)
        packed = glen.astype(info.dtype) | need << 8
        packed[big] = 1 | (need[big] + 1) << 8
        self.info[out] = packed
        self.mat[out[big]] = True

    def flush(self, wires: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Materialized wires of the finished layer ``wires`` as (outs, terms, term counts),
        one entry per sub-step; resets the layer."""
        mat = wires[self.mat[wires]]
        out = []
        if mat.size:
            info = self.info[mat]
            need = (info >> 8) - ((info & 0xFF) == 1).astype(info.dtype)  # cut: need + 1
            order, starts, ends = _groups(need)
            mat = mat[order]
            lens = self.elen[mat]
            ends_t = np.cumsum(lens, dtype=np.int32)
            idx = np.repeat(self.estart[mat] - ends_t + lens, lens)
            idx += np.arange(idx.size, dtype=np.int32)
            terms = self.buf.view[idx]
            ptr = np.concatenate([[0], ends_t])
            for s, e in zip(starts, ends):
                out.append((mat[s:e], terms[ptr[s] : ptr[e]], lens[s:e]))
        self.info[wires] = 1
        self.buf.n = 0
        return out


def _fold(c: Circuit, max_terms: int) -> _Plan:
    F, D = c.first_gate_wire, c.depth() + 1
    folder = _Folder(c, max_terms)
    order, and_ptr, lin_ptr = _depth_order(c)
    kinds, los, his, term_los = [], [], [], []
    # the plan's largest arrays: little spare capacity, as they peak with the folder's
    lin_outs, lin_terms = _Growable(np.int32, growth=1.25), _Growable(np.int32, growth=1.25)
    lin_lens = _Growable(np.uint8, growth=1.25)
    lin_rows = 0
    for d in range(D):
        layer = order[lin_ptr[d] : lin_ptr[d + 1]]
        if layer.size:
            by_xor, starts, ends = _groups(c.xor_depth[layer])
            layer = layer[by_xor]
            for s, e in zip(starts.tolist(), ends.tolist()):
                folder.add_gates(layer[s:e])
            for outs, terms, lens in folder.flush(layer + F):
                kinds.append(LINEAR_STEP)
                term_los.append(lin_terms.n)
                los.append(lin_rows)
                lin_rows += len(outs)
                his.append(lin_rows)
                lin_outs.extend(outs)
                lin_terms.extend(terms)
                lin_lens.extend(lens)
        if d + 1 < D and and_ptr[d + 2] > and_ptr[d + 1]:
            kinds.append(AND_STEP)
            term_los.append(lin_terms.n)
            los.append(and_ptr[d + 1])
            his.append(and_ptr[d + 2])

    del folder
    lin_out, lin_lens, lin_terms = lin_outs.freeze(), lin_lens.freeze(), lin_terms.freeze()
    and_g = order[: and_ptr[-1]]
    return _Plan(
        kind=np.array(kinds, np.uint8), lo=np.array(los, np.int64), hi=np.array(his, np.int64),
        and_out=and_g + F, and_a=c.a[and_g], and_b=c.b[and_g], lin_out=lin_out,
        lin_lens=lin_lens, lin_terms=lin_terms, term_lo=np.array(term_los, np.int64))


def _order_rows(c: Circuit, plan: _Plan) -> np.ndarray:
    """Reorder the rows of every step in place, walking steps backwards, and return each
    wire's death: the step of its last read (-1: never read; ``len(plan.kind)``: output).

    A step's rows are sorted by (term count, death, position of the last read), where a
    step's reads are numbered column by column (AND: every ``a`` then every ``b``; linear:
    per term count, term 0 of every row, then term 1, ...). Wires that die together then
    sit next to each other in the order their last reader reads them, so one contiguous
    block of slots holds them and that reader sees runs of consecutive slots.
    """
    S = len(plan.kind)
    if 256 * (S + 1) >= 2**32:
        raise ValueError(f"schedule has {S} steps: too many for the row sort key")
    death = np.full(c.n_wires, -1, np.int32)
    pos = np.zeros(c.n_wires, np.int32)
    outs = c.outputs
    death[outs] = S
    pos[outs[::-1]] = np.arange(outs.size, dtype=np.int32)[::-1]
    for t in range(S - 1, -1, -1):
        lo, hi = int(plan.lo[t]), int(plan.hi[t])
        if plan.kind[t] == AND_STEP:
            order = _row_order(plan.and_out[lo:hi], death, pos, t)
            for arr in (plan.and_out, plan.and_a, plan.and_b):
                arr[lo:hi] = arr[lo:hi][order]
            reads = np.concatenate([plan.and_a[lo:hi], plan.and_b[lo:hi]])
        else:
            reads = _order_linear(plan, lo, hi, death, pos, t)
        idx = np.flatnonzero(death[reads] < 0).astype(np.int32)
        new = reads[idx]
        pos[new[::-1]] = idx[::-1]  # position of (one of) its reads here
        death[new] = t
    return death


def _row_order(out: np.ndarray, death: np.ndarray, pos: np.ndarray, t: int,
               lens: np.ndarray | None = None, n_steps: int = 0) -> np.ndarray:
    """Row permutation of step t: by (term count,) death, last-read position; rows never
    read keep their order and die at t. One int64 key: death <= n_steps, term count
    < 256 and position < 2**31. Keys are distinct (a read position holds one wire; rows
    read later die after t), so an unstable sort (SIMD quicksort, twice as fast) gives
    the same order."""
    d = death[out].astype(np.int64)
    unread = d < 0
    d[unread] = t
    if lens is not None:
        d += lens.astype(np.int64) * (n_steps + 1)
    p = pos[out]
    p[unread] = np.flatnonzero(unread)
    d <<= 31
    d |= p
    return np.argsort(d)


def _order_linear(plan: _Plan, lo: int, hi: int, death: np.ndarray, pos: np.ndarray,
                  t: int) -> np.ndarray:
    """Reorder the rows of linear step t (CSR terms move with them); returns its reads
    numbered column by column within each term count."""
    terms = plan.terms_of(t)
    lens = plan.lin_lens[lo:hi].astype(np.int64)
    order = _row_order(plan.lin_out[lo:hi], death, pos, t, lens, len(plan.kind))
    plan.lin_out[lo:hi] = plan.lin_out[lo:hi][order]
    old_start = (np.cumsum(lens) - lens)[order]
    lens = lens[order]
    plan.lin_lens[lo:hi] = lens
    ends = np.cumsum(lens)
    idx = np.repeat(old_start - ends + lens, lens) + np.arange(terms.size)
    terms[:] = terms[idx]
    cuts = np.flatnonzero(lens[1:] != lens[:-1]) + 1
    bounds = np.concatenate([[0], cuts, [hi - lo]])
    cols = [terms[ends[r0] - lens[r0] : ends[r1 - 1]].reshape(r1 - r0, lens[r0]).T.ravel()
            for r0, r1 in pairwise(bounds.tolist())]
    return np.concatenate(cols)


class _FreeSpace:
    """Free slot extents (sorted, coalesced): best-fit allocation of contiguous blocks."""

    def __init__(self, n_slots: int) -> None:
        self.start = np.zeros(0, np.int64)
        self.size = np.zeros(0, np.int64)
        self.n_slots = n_slots

    def release(self, start: np.ndarray, size: np.ndarray) -> None:
        if not start.size:
            return
        start = np.concatenate([self.start, start])
        size = np.concatenate([self.size, size])
        keep = size > 0
        start, size = start[keep], size[keep]
        order = np.argsort(start, kind="stable")
        start, size = start[order], size[order]
        if start.size:
            first = np.concatenate([[True], start[1:] != start[:-1] + size[:-1]])
            heads = np.flatnonzero(first)
            start, size = start[heads], np.add.reduceat(size, heads)
        self.start, self.size = start, size

    def take(self, n: int) -> int:
        """First slot of a free block of n slots; grows the slot space when none fits."""
        fits = np.flatnonzero(self.size >= n)
        if fits.size:
            i = fits[np.argmin(self.size[fits])]
            s = int(self.start[i])
            self.start[i] += n
            self.size[i] -= n
            return s
        s = self.n_slots
        if self.size.size and self.start[-1] + self.size[-1] == s:
            s = int(self.start[-1])
            self.start, self.size = self.start[:-1], self.size[:-1]
        self.n_slots = s + n
        return s


def _allocate_slots(c: Circuit, plan: _Plan, death: np.ndarray,
                    reuse: bool) -> tuple[np.ndarray, int]:
    """Map every scheduled wire to a slot; returns (slot_of over wire ids, n_slots).

    Each run of a step's rows that die at the same step gets one contiguous block, taken
    from slots freed before the step (never from slots the step itself reads, so an
    executor may write outputs as it goes). A block is freed after its death step.
    """
    F, S = FIRST_INPUT + c.n_inputs, len(plan.kind)
    slot_of = np.full(c.n_wires, -1, np.int32)
    slot_of[:F] = np.arange(F, dtype=np.int32)
    space = _FreeSpace(F)
    freed: list[list[tuple[int, int]]] = [[] for _ in range(S + 1)]
    # inputs and constants: runs of equal death, released after that step
    d_in = death[:F]
    cuts = np.concatenate([[0], np.flatnonzero(d_in[1:] != d_in[:-1]) + 1, [F]])
    run_d = d_in[cuts[:-1]]
    mortal = run_d < S
    in_start, in_size, in_when = cuts[:-1][mortal], np.diff(cuts)[mortal], run_d[mortal] + 1
    for s in range(S):
        lo, hi = int(plan.lo[s]), int(plan.hi[s])
        out = (plan.and_out if plan.kind[s] == AND_STEP else plan.lin_out)[lo:hi]
        if reuse:
            now = in_when == s
            blocks = np.array(freed[s], np.int64).reshape(-1, 2)
            freed[s] = []
            space.release(np.concatenate([in_start[now], blocks[:, 0]]),
                          np.concatenate([in_size[now], blocks[:, 1]]))
        d = death[out]
        d[d < 0] = s
        cuts = np.concatenate([[0], np.flatnonzero(d[1:] != d[:-1]) + 1, [out.size]])
        for r0, r1 in zip(cuts[:-1].tolist(), cuts[1:].tolist()):
            first = space.take(r1 - r0)
            slot_of[out[r0:r1]] = np.arange(first, first + r1 - r0, dtype=np.int32)
            if d[r0] < S:
                freed[d[r0] + 1].append((first, r1 - r0))
    return slot_of, space.n_slots


def _to_slots(slot_of: np.ndarray, arr: np.ndarray, chunk: int = 1 << 22) -> None:
    """``slot_of[arr]`` written over arr, a chunk at a time (no full-size temporaries)."""
    for i in range(0, arr.size, chunk):
        arr[i : i + chunk] = slot_of[arr[i : i + chunk]]
