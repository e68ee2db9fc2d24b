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


def prefix_carries(b: CircuitBuilder, x: Word, y: Word, cin=ZERO) -> Word:
    """Carries into bits 0..n of x + y + cin (n+1 wires), Sklansky tree."""
    x, y = _align(x, y, False)
    cin = wires(cin)
    lead = np.broadcast_shapes(x.shape[:-1], cin.shape)
    x = np.broadcast_to(x, lead + x.shape[-1:])
    y = np.broadcast_to(y, lead + y.shape[-1:])
    # fold the carry in as a generate at position -1
    g = np.concatenate([np.broadcast_to(cin, lead)[..., None], b.and_(x, y)], axis=-1)
    p = np.concatenate([np.zeros(lead + (1,), np.int32), b.xor(x, y)], axis=-1)
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
