"""Sklansky parallel-prefix adder: ceil(log2 n)+1 AND levels instead of n.

Generate g = x & y and propagate p = x ^ y; the prefix operator
(g, p) o (g', p') = (g ^ (p & g'), p & p') needs 2 AND gates (g and p & g' never both
hold, so OR is XOR). Sklansky's divide-and-conquer tree has (n/2) log2 n operator nodes,
so the adder spends about n + n log2 n AND gates for log-depth carries: use it where the
adder sits on a long sequential chain (division, square root iterations).
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit import ZERO, CircuitBuilder

from .integer import _align
from .words import Word, wires


def _generate_propagate(b: CircuitBuilder, x: Word, y: Word, cin) -> tuple[Word, Word]:
    """Per-bit (generate, propagate) of x + y, with the carry-in folded in as a generate at
    position -1 (so both have n+1 wires)."""
    x, y = _align(x, y, False)
    cin = wires(cin)
    lead = np.broadcast_shapes(x.shape[:-1], cin.shape)
    x = np.broadcast_to(x, lead + x.shape[-1:])
    y = np.broadcast_to(y, lead + y.shape[-1:])
    g = np.concatenate([np.broadcast_to(cin, lead)[..., None], b.and_(x, y)], axis=-1)
    p = np.concatenate([np.zeros(lead + (1,), np.int32), b.xor(x, y)], axis=-1)
    return g, p


def prefix_carries(b: CircuitBuilder, x: Word, y: Word, cin=ZERO) -> Word:
    """Carries into bits 0..n of x + y + cin (n+1 wires), Sklansky tree."""
    g, p = _generate_propagate(b, x, y, cin)
    n = g.shape[-1]
    span = 1
    while span < n:
        # positions whose block (size 2*span) upper half takes the lower half's last prefix
        idx = np.arange(n)
        upper = (idx // span) % 2 == 1
        src = (idx // span) * span - 1
        tgt = idx[upper]
        s = src[upper]
        gs, ps = g[..., s], p[..., s]
        gt, pt = g[..., tgt], p[..., tgt]
        g = g.copy()
        p = p.copy()
        g[..., tgt] = b.xor(gt, b.and_(pt, gs))
        p[..., tgt] = b.and_(pt, ps)
        span *= 2
    return g  # g[i] = carry into bit i (i = 0 is cin), g[n-1+1]... see below


def add_fast(b: CircuitBuilder, x: Word, y: Word, cin=ZERO) -> Word:
    """x + y + cin mod 2^n with log-depth carries."""
    x, y = _align(x, y, False)
    c = prefix_carries(b, x[..., :-1], y[..., :-1], cin) if x.shape[-1] > 1 else \
        np.broadcast_to(wires(cin), x.shape[:-1])[..., None]
    return b.xor(b.xor(x, y), c)


def prefix_and(b: CircuitBuilder, x: Word) -> Word:
    """Inclusive prefix ANDs x0, x0&x1, ... (Sklansky): log-depth, (n/2)log2 n AND gates."""
    x = wires(x)
    n = x.shape[-1]
    span = 1
    while span < n:
        idx = np.arange(n)
        upper = (idx // span) % 2 == 1
        src = (idx // span) * span - 1
        x = x.copy()
        x[..., idx[upper]] = b.and_(x[..., idx[upper]], x[..., src[upper]])
        span *= 2
    return x


def increment_fast(b: CircuitBuilder, x: Word, inc=ZERO) -> tuple[Word, np.ndarray]:
    """(x + inc mod 2^n, carry out) for a 1-bit ``inc`` with log-depth carries."""
    x = wires(x)
    inc = np.broadcast_to(wires(inc), x.shape[:-1])
    c = prefix_and(b, np.concatenate([inc[..., None], x], axis=-1))
    return b.xor(x, c[..., :-1]), c[..., -1]


def carry_out_tree(b: CircuitBuilder, x: Word, y: Word, cin=ZERO) -> np.ndarray:
    """Carry out of x + y + cin by a balanced (generate, propagate) reduction tree.

    Log depth like the Sklansky adder but only the last carry: about 3n AND gates
    instead of n log2 n. This is the fast comparator (x >= y is the carry of x + ~y + 1).
    """
    g, p = _generate_propagate(b, x, y, cin)
    while g.shape[-1] > 1:
        n = g.shape[-1]
        lo_g, hi_g = g[..., 0 : n - 1 : 2], g[..., 1:n:2]
        lo_p, hi_p = p[..., 0 : n - 1 : 2], p[..., 1:n:2]
        ng = b.xor(hi_g, b.and_(hi_p, lo_g))
        np_ = b.and_(hi_p, lo_p) if n > 2 else np.zeros_like(ng)
        if n % 2:
            ng = np.concatenate([ng, g[..., -1:]], axis=-1)
            np_ = np.concatenate([np_, p[..., -1:]], axis=-1)
        g, p = ng, np_
    return g[..., 0]
