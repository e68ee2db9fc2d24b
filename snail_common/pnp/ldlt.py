"""LDL^T solve of a symmetric 6x6 system, arranged for a short dependency chain.

Right-looking elimination: at column j the products A[j,i] * A[j,k] of every trailing
update are formed while 1/d_j is still being computed, so each column costs one division,
one multiplication and one subtraction of AND-depth; the right-hand side is eliminated in
the same batches (forward substitution for free), and back substitution is right-looking
too (when x_k is known, every z_i with i < k is updated at once).
"""

from __future__ import annotations

from .fops import F, stack
from .normal import UPPER


def ldlt_solve(packed: F, rhs: F) -> F:
    """x with A x = rhs, for A given as its UPPER-packed (21,) entries; rhs (6,)."""
    a = {e: packed[p] for p, e in enumerate(UPPER)}
    z = [rhs[i] for i in range(6)]
    recip: list[F] = []
    mult: dict[tuple[int, int], F] = {}  # mult[(k, i)] = L[k, i] = A[i, k] / d_i
    for j in range(6):
        recip.append(1.0 / a[j, j])
        if j == 5:
            break
        rows = range(j + 1, 6)
        updates = [(i, k) for i in rows for k in range(i, 6)]
        left = [a[j, i] for i, _ in updates] + [a[j, i] for i in rows]
        right = [a[j, k] for _, k in updates] + [z[j] for _ in rows]
        prods = stack(left) * stack(right)
        scaled = stack([*(prods[p] for p in range(len(left))), *(a[j, i] for i in rows)])
        scaled = scaled * recip[j]
        old = stack([a[e] for e in updates] + [z[i] for i in rows])
        new = old - scaled[0:len(left)]
        for p, e in enumerate(updates):
            a[e] = new[p]
        for q, i in enumerate(rows):
            z[i] = new[len(updates) + q]
            mult[i, j] = scaled[len(left) + q]
    y = stack(z) * stack(recip)
    x = [y[i] for i in range(6)]
    for k in range(5, 0, -1):
        lower = list(range(k))
        upd = stack([x[i] for i in lower]) - stack([mult[k, i] for i in lower]) * x[k]
        for q, i in enumerate(lower):
            x[i] = upd[q]
    return stack(x)
