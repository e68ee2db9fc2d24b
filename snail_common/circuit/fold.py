"""Folding: the circuit's gates as steps over wire ids, before slots are allocated.

AND gates are grouped by AND-depth; the XOR/NOT logic between two AND layers is expanded
into multi-input XORs over leaf wires (see schedule.py for the rules: which wires are
materialized, how long an expression may grow before it is cut).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .builder import _Growable
from .ir import AND, Circuit

LINEAR_STEP = 0
AND_STEP = 1
MAX_TERMS = 16
MAX_TERMS_SHARED = 4


class FoldedPlan(NamedTuple):
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


def fold(c: Circuit, max_terms: int) -> FoldedPlan:
    """The steps of ``c`` over wire ids (AND layers and folded linear layers)."""
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
    return FoldedPlan(
        kind=np.array(kinds, np.uint8), lo=np.array(los, np.int64), hi=np.array(his, np.int64),
        and_out=and_g + F, and_a=c.a[and_g], and_b=c.b[and_g], lin_out=lin_out,
        lin_lens=lin_lens, lin_terms=lin_terms, term_lo=np.array(term_los, np.int64))
