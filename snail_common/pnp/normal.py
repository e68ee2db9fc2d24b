"""Weighted normal equations of the reprojection cost, per point then summed over points.

For a camera point (x, y, z), with a = x/z, b = y/z, c = 1/z, the Jacobian rows of the
normalized residual w.r.t. the step (v, w) of types.py are
    ju = [c, 0, -a c, -a b, 1 + a^2, -b]      jv = [0, c, -b c, -(1 + b^2), a b, a].
Each row has one structural zero, so a point contributes 15 + 15 products to the 21 upper
entries of J^T W J (10 of them shared), 5 + 5 to J^T W r and 2 to the cost; all points are
computed in one batch and summed with a log-depth tree. The weighted residual w r is
formed once and shared by the gradient and the cost.

Precision (DESIGN 6): the camera points, residuals and cost are float32. The Jacobian and
both sums J^T W J and J^T W r are computed in a narrow float (NORMAL_FRAC fraction bits;
a narrow multiply costs less than half a float32 one, an add two thirds). An error of
2^-14 in J^T W J only slows convergence a little; in J^T W r it moves the fixed point
J^T W r = 0 by about 2^-14 of the pose's own noise-driven uncertainty, which changes the
reprojection error only to second order. The accuracy tests hold this against OpenCV.
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
# Pair (1, 4) of either row is the (2, 5) entry, a b c times the weight: minus pair (0, 2)
# of ju (the (0, 3) entry) and minus pair (0, 3) of jv (the (1, 4) entry).
_COMPUTED = [pair for pair in _PAIRS if pair != (1, 4)]
_MIRRORED = (_COMPUTED.index((0, 2)), _COMPUTED.index((0, 3)))
_LEFT = np.array([i for i, _ in _COMPUTED])
_RIGHT = np.array([k for _, k in _COMPUTED])
_U_AT = {(c,): i for i, c in enumerate(_U_COLS)}
_V_AT = {(c,): i for i, c in enumerate(_V_COLS)}
# Fraction bits of J, J^T W J and J^T W r (module doc). With all of them rounded to 13
# bits, 600 random scenes in float64 emulation were all as accurate as OpenCV; 11 bits
# missed some and needed up to 20 iterations.
NORMAL_FRAC = 13


def _pair_index(cols: list[int]) -> dict[tuple[int, int], int]:
    """(row, col) of the 6x6 matrix -> index into one row's pair products: the 14 of
    _COMPUTED, then the mirrored one."""
    order = [*_COMPUTED, (1, 4)]
    return {(cols[i], cols[k]): p for p, (i, k) in enumerate(order)}


def camera_points(R: F, t: F, world: F) -> F:
    """X_c = R X + t for every point, (n, 3): ((r0 x0 + r1 x1) + (r2 x2 + t)) per row."""
    prods = R[None] * world[:, None, :]
    return (prods[:, :, 0] + prods[:, :, 1]) + (prods[:, :, 2] + t[None, :])


def residuals(R: F, t: F, image: F, world: F) -> tuple[F, F, F]:
    """Normalized projections (n, 2), residuals (n, 2) and inverse depths (n,)."""
    return project(camera_points(R, t, world), image)


def project(xc: F, image: F) -> tuple[F, F, F]:
    """residuals() from the camera points ``xc`` (n, 3)."""
    inv_z = 1.0 / xc[:, 2]
    proj = xc[:, 0:2] * inv_z[:, None]
    return proj, proj - image, inv_z


def jacobian(proj: F, c: F) -> F:
    """J (n, 2, 5): the ju and jv rows without their structural zeros, from the projections
    and inverse depths rounded to the current precision and computed in it."""
    frac = c.be.frac
    a, b, c = proj[:, 0].round(frac), proj[:, 1].round(frac), c.round(frac)
    prods = stack([a, b, a, a, b], 1) * stack([a, b, b, c, c], 1)
    aa, bb, ab, ac, bc = (prods[:, i] for i in range(5))
    one_plus = stack([aa, bb], 1) + 1.0
    ju = stack([c, -ac, -ab, one_plus[:, 0], -b], 1)
    jv = stack([c, -bc, -one_plus[:, 1], ab, a], 1)
    return stack([ju, jv], 1)


def normal_equations(R: F, t: F, image: F, world: F, weights: F) -> tuple[F, F, F]:
    """(J^T W J packed as UPPER (21,), J^T W r (6,), cost = r^T W r ()) at the pose (R, t).

    ``weights`` is (n, 2): per point and axis (the client folds fx^2, fy^2 and any robust or
    padding weight into it), so the cost is in squared pixels. Residuals and cost are
    float32; J, J^T W J and J^T W r are NORMAL_FRAC narrow (see the module doc).
    """
    proj, err, c = residuals(R, t, image, world)
    werr = err * weights
    cost_pt = werr * err  # (n, 2)
    cost = (cost_pt[:, 0] + cost_pt[:, 1]).sum(0)
    with R.be.narrow(NORMAL_FRAC):
        jac = jacobian(proj, c)
        hess = _hessian(jac, weights.round(NORMAL_FRAC)).sum(0)
        gpart = jac * werr.round(NORMAL_FRAC)[:, :, None]  # (n, 2, 5)
        grad = _combine(gpart[:, 0], gpart[:, 1], _U_AT, _V_AT, [(i,) for i in range(6)])
        grad = grad.sum(0)
    zero = const(R.be, 0.0, (1,))
    return concat([hess[0:1], zero, hess[1:]]), grad, cost  # UPPER[1] = (0, 1) is always 0


def _hessian(jac: F, weights: F) -> F:
    """Per-point J^T W J entries (n, 20) in the order of _NONZERO. Each row's (2, 5)
    product is minus another product of the row (_MIRRORED), so 28 products are computed
    instead of 30."""
    wjac = jac * weights[:, :, None]
    hpair = wjac[:, :, _LEFT] * jac[:, :, _RIGHT]  # (n, 2, 14)
    mirrored = stack([hpair[:, 0, _MIRRORED[0]], hpair[:, 1, _MIRRORED[1]]], 1)
    hpair = concat([hpair, -mirrored[:, :, None]], 2)
    return _combine(hpair[:, 0], hpair[:, 1], _pair_index(_U_COLS), _pair_index(_V_COLS),
                    _NONZERO)


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
