"""Weighted normal equations of the reprojection cost, per point then summed over points.

For a camera point (x, y, z), with a = x/z, b = y/z, c = 1/z, the Jacobian rows of the
normalized residual w.r.t. the step (v, w) of types.py are
    ju = [c, 0, -a c, -a b, 1 + a^2, -b]      jv = [0, c, -b c, -(1 + b^2), a b, a].
Each row has one structural zero, so a point contributes 15 + 15 products to the 21 upper
entries of J^T W J (10 of them shared), 5 + 5 to J^T W r and 2 to the cost; all points are
computed in one batch and summed with a log-depth tree.
"""

from __future__ import annotations

import numpy as np

from .fops import F, concat, const, stack

# Upper-triangle entries of a symmetric 6x6 matrix, row-major: the packed layout everywhere.
UPPER = [(i, k) for i in range(6) for k in range(i, 6)]
_U_COLS = [0, 2, 3, 4, 5]  # columns of the step where ju is not structurally zero
_V_COLS = [1, 2, 3, 4, 5]
_PAIRS = [(i, k) for i in range(5) for k in range(i, 5)]  # upper pairs inside a 5-vector
_NONZERO = [e for e in UPPER if e != (0, 1)]  # ju and jv never both touch v_x and v_y


def _pair_index(cols: list[int]) -> dict[tuple[int, int], int]:
    """(row, col) of the 6x6 matrix -> index into the 15 pair products of one residual row."""
    return {(cols[i], cols[k]): p for p, (i, k) in enumerate(_PAIRS)}


def camera_points(R: F, t: F, world: F) -> F:
    """X_c = R X + t for every point, (n, 3): ((r0 x0 + r1 x1) + (r2 x2 + t)) per row."""
    prods = R[None] * world[:, None, :]
    return (prods[:, :, 0] + prods[:, :, 1]) + (prods[:, :, 2] + t[None, :])


def residuals(R: F, t: F, image: F, world: F) -> tuple[F, F, F]:
    """Normalized projections (n, 2), residuals (n, 2) and inverse depths (n,)."""
    xc = camera_points(R, t, world)
    inv_z = 1.0 / xc[:, 2]
    proj = xc[:, 0:2] * inv_z[:, None]
    return proj, proj - image, inv_z


def normal_equations(R: F, t: F, image: F, world: F, weights: F) -> tuple[F, F, F]:
    """(J^T W J packed as UPPER (21,), J^T W r (6,), cost = r^T W r ()) at the pose (R, t).

    ``weights`` is (n, 2): per point and axis (the client folds fx^2, fy^2 and any robust or
    padding weight into it), so the cost is in squared pixels.
    """
    proj, err, c = residuals(R, t, image, world)
    a, b = proj[:, 0], proj[:, 1]
    lhs = stack([a, b, a, a, b], 1)
    rhs = stack([a, b, b, c, c], 1)
    prods = lhs * rhs
    aa, bb, ab, ac, bc = (prods[:, i] for i in range(5))
    one_plus = stack([aa, bb], 1) + 1.0
    ju = stack([c, -ac, -ab, one_plus[:, 0], -b], 1)
    jv = stack([c, -bc, -one_plus[:, 1], ab, a], 1)
    jac = stack([ju, jv], 1)  # (n, 2, 5)
    wjac = jac * weights[:, :, None]
    left = np.array([i for i, _ in _PAIRS])
    right = np.array([k for _, k in _PAIRS])
    hpair = wjac[:, :, left] * jac[:, :, right]  # (n, 2, 15)
    gpart = wjac * err[:, :, None]  # (n, 2, 5)
    werr = err * weights
    cost_pt = werr * err  # (n, 2)

    hess = _combine(hpair[:, 0], hpair[:, 1], _pair_index(_U_COLS), _pair_index(_V_COLS),
                    _NONZERO)
    grad = _combine(gpart[:, 0], gpart[:, 1], {(c,): i for i, c in enumerate(_U_COLS)},
                    {(c,): i for i, c in enumerate(_V_COLS)}, [(i,) for i in range(6)])
    per_point = concat([hess, grad, (cost_pt[:, 0] + cost_pt[:, 1])[:, None]], 1)
    total = per_point.sum(axis=0)
    nz = len(_NONZERO)
    zero = const(total.be, 0.0, (1,))
    hess_sum = concat([total[0:1], zero, total[1:nz]])  # UPPER[1] = (0, 1) is always zero
    return hess_sum, total[nz:nz + 6], total[nz + 6]


def _combine(u: F, v: F, u_at: dict, v_at: dict, keys: list[tuple]) -> F:
    """Entries keyed by ``keys``: u-term + v-term where both rows contribute (one batched
    add), the single term where only one does. Returns (n, len(keys))."""
    both = [k for k in keys if k in u_at and k in v_at]
    summed = u[:, [u_at[k] for k in both]] + v[:, [v_at[k] for k in both]]
    only_u = [k for k in keys if k in u_at and k not in v_at]
    only_v = [k for k in keys if k in v_at and k not in u_at]
    parts = concat([summed, u[:, [u_at[k] for k in only_u]], v[:, [v_at[k] for k in only_v]]], 1)
    order = {k: i for i, k in enumerate(both + only_u + only_v)}
    return parts[:, [order[k] for k in keys]]
