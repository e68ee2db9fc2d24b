"""The normal equations with fixed-point per-point work (circuit ``nx-sil-nN``).

Same quantities as normal.py, computed differently where precision allows (fixed.py):
- camera points R X + t in fixed point, rounded once to float32 (``camera_points_fixed``):
  truncated integer products (fixed.mul_cut) and exact sums cost 5.8 k AND per point
  (7.1 k with a 26-bit map and products at its unit, GUARD 3) against 12.9 k for
  float32. The map is taken at W_MAP = 24 bits: its truncation is the same at every pose
  (a map moved by 2^-23 of its radius, far below any map's own error), so it shifts the
  cost by a smooth amount: against float64 at OpenCV's optimum (200 scenes) the median
  relative error is 1.4e-5 and the largest 2.0e-4 (8.5e-6 and 1.2e-4 with 26 bits), but
  along a line of rotations through the optimum the cost's departure from a smooth
  parabola (what decides an accept/reject) has a median of 7.3e-6 and a largest of
  7.9e-5 of the cost (26 bits: 6.0e-6 and 6.5e-5; a 24-bit map with products at its
  unit: 1.2e-5 and 9.9e-5, hence W_XC), and a relative rise of 1e-4 is always seen
  (test_the_cost_resolves_a_relative_change_of_1e_4). 1,000 scenes per algorithm: seeds
  1 and 3 and the in-circuit solve (seed 1) as with 26 bits; seed 2 lost GN scene 54
  (n = 4, planar, at the 20-iteration cap with 26 bits too: 0.466 px against OpenCV's
  0.421). The client's map is
  centered with unit RMS radius (preprocess.py), but a map owner's selection can reach
  far out, so the map enters as block floating point (one exponent for all its
  coordinates) and t at the same scale with T_BITS more integer bits: it saturates only
  for a camera 2^11 map radii away, where no point spread could be resolved anyway.
  Where the client solves, it passes the map in that form (``map_fixed``: the integers
  the circuit would compute, so the same sums bit for bit), which saves the conversion,
  0.65 k AND per point (the in-circuit family and the map owner's ``-mo`` keep the
  float32 map);
- float32: the projections a = x/z, b = y/z, each one correctly rounded division (two
  divisions cost 0.3 k AND per point less than 1/z and two products, and round once),
  and the residuals r = a - u, whose float32 rounding of a, about 2^-24 |a| against
  residuals of 1e-3, sets the cost's precision (relative errors of ~1e-5; driver.py's
  cost_tol is 1e-4);
- the cost in fixed point: (sqrt(w) r)^2 with r as block floating point at W_RC = 20
  bits of the largest residual (``er``), sqrt(w) the 16-bit ``wfix``, sqrt(w) r kept to
  20 bits (truncated: fixed.mul_cut_sm) and squared truncated 2^D_COST below the
  per-point cost's unit of 2^-28 of the largest, then an exact sum: 1.5 k AND per point
  against 4.1 k for float32 products and a block fixed-point sum (2.0 k with all 24 of
  the largest residual's float32 bits and a unit of 2^-32). With sigma = sqrt(w) r / u
  (u the residuals' unit, at most 2^(1 - W_RC) of the largest |r|), sqrt(w) r comes out
  less than 3 units below sigma, which loses less than 6 sigma u^2 of w r^2, and its
  square less than 2 units of 2^D_COST: with equal weights the cost is within 6 sqrt(2n)
  2^(1 - W_RC) + n 2^(D_COST + 4 - 2 W_RC) below the exact sum of the float32 residuals'
  squares (2.7e-4 at n = 256, where every error would have to align; measured: at most
  1.0e-5, 3e-7 with 24 bits; tests/test_loc_fixed.py), the size of the residuals' own
  float32 error: against the float64 cost at OpenCV's optimum (200 random scenes) the
  median relative error went from 5.2e-6 to 8.5e-6, the 99th percentile from 6.3e-5 to
  6.7e-5 and the largest stayed 1.2e-4, and a pose whose float64 cost is 1e-4 higher
  costs more (400 of 400; test_the_cost_resolves_a_relative_change_of_1e_4). 1,000
  scenes per algorithm, seeds 1 and 2, converged as with 24 bits; 19 and 18 bits made
  the median error 3 and 5 times larger. It is the cost of the weights' square roots
  rounded to 16 bits relative to the largest (relative error of w below 2^-15 / sqrt(w /
  w_max), none where all weights are equal, as without lens distortion and with fx =
  fy): the cost the result reports and the accept/reject decisions, which compare two
  costs of the same weights; the result's reprojection RMS is computed from the final
  pose in float64, not from it;
- fixed point: the Jacobian, J^T W J and J^T W r, at about 13 significant bits, the
  precision normal.py's narrow floats already had. The Jacobian is sqrt(w) J: sqrt(w)
  multiplies c, a and b (6 products per point) and the rest is built from those (6
  more), 12 products instead of 5 for J and 10 for W J, all exact floors (truncated
  products there lost GN scenes), J^T W J = (sqrt(w) J)^T (sqrt(w) J) and J^T W r =
  (sqrt(w) J)^T (sqrt(w) r) (J^T W r's residuals: W_R = 15 bits of
  the largest, truncated from the cost's; W_RS = 13 when the client solves, which shrinks
  each by less than 2^-12 of the largest: a shift of the converged pose far below its
  noise). Projections a, b enter at a public
  scale (2^-13, saturating at |a| = 2, 63 degrees off the optical axis: only the step of
  such a point degrades, never the cost); inverse depths and residuals as block floating
  point, each block sharing its largest exponent, which the circuit returns (``ec``,
  ``er``) so the client can scale the sums back. The inverse depths need no float
  division: fixed.recip_block divides 2^(W_C + 23) by z's significand in W_C + 1
  non-restoring steps and shifts by z's exponent above the block's smallest, the floor of
  the exact 1/z (0.5 k AND per point against 0.9 k for a float32 1/z converted);
- when the client solves, J^T W J from the Jacobian's magnitudes H_SHIFT bits shorter
  (free: the low wires are left out), which makes its 38 products per point about a third
  cheaper. J^T W J only sets how fast the iteration converges, J^T W r where it converges:
  at 10 bits (against 13) 2 x 1,000 random scenes (seeds 1 and 2, LM and GN) were as
  accurate as before and needed as many iterations; shift 4 lost a GN scene and left one
  unconverged (seed 2), shift 5 lost two (seed 1). The in-circuit solve keeps all 13 bits:
  with the shift, its LM (x10 / /10 damping) ended at the 20-iteration cap on 2 of 1,000
  scenes (seed 1) where it converges. The products of J^T W J and J^T W r are truncated
  (fixed.mul_cut, GUARD and H_GUARD), each row of J^T W J's with one shared multiplicand;
- the client passes the square roots of its weights normalized to a largest weight of 1
  as 16-bit integers (``wfix``, 2^F_W for 1): the cost takes all 16 bits, the Jacobian
  the top W_WS = 10 (a free truncation; sqrt(w) r is the cost's, shortened). The float32
  weights stay an input (unused by this circuit; the client decodes with their largest,
  ``weight_unit``).

Outputs are integers: ``hess`` (21, packed as normal.UPPER) at scale
2^(s_i + s_k + DROP), ``grad`` (6) at 2^(s_i + sr + DROP), where s is the column scale
(translation columns: the inverse depths' block scale; rotation columns: 2^-F_A) and sr
the residuals' block scale (``scales`` computes them; ``decode``), and ``cost`` at
2^(D_COST + 2 src), src the residuals' block scale at W_RC bits; all three are of the
normalized weights (times the largest weight in the client's units).
"""

from __future__ import annotations

import numpy as np

from .fixed import SCALE_BIAS, SM, TC, fix_backend
from .fops import F, MirrorBackend, concat
from .normal import UPPER

F_A = 13  # fraction bits of the projections a = x/z, b = y/z
W_A = 14  # their magnitude bits: |a| < 2
EMAX_A = W_A + SCALE_BIAS - F_A  # the float exponent at the top of that scale
W_C = 15  # inverse depths, relative to the largest one
W_R = 15  # residuals in J^T W r, relative to the largest one, in the in-circuit solve
W_RS = 13  # when the client solves (2 x 1,000 scenes per algorithm as with 15 bits, as
# many iterations; 11 bits took more and lost a GN scene; the in-circuit solve's LM and GN
# took 2 and 3 % more iterations with 13 and one GN scene hit the cap)
W_RC = 20  # residuals in the cost, relative to the largest (module doc: the cost)
F_W = 15  # square roots of the weights: the largest is 2^15 (module doc: the cost)
W_W = 16
W_WS = 10  # their top bits scale the sums (1,000 random scenes per algorithm converged as
# with 15 bits)
D_COST = 12  # bits dropped by w r times r: a per-point cost is within 2^-24 of the largest
DROP = F_A  # bits dropped by every pair product of J^T W J and J^T W r
HESS_BITS = 31  # to_float's integers are at most 2^31 in magnitude (float_system)
H_SHIFT = 3  # J^T W J's Jacobian magnitudes are this much shorter when the client solves
F_ROT = 24  # fraction bits of the rotation entries: all of float32's for |r| in [1/2, 1]
W_MAP = 24  # map coordinates, relative to the largest one's binade (module doc)
W_XC = W_MAP + 1  # camera points' bits at that binade: R X's products keep one bit more
X_GUARD = 2  # R_ij X_j keeps the partial products from X_GUARD bits below its unit
GUARD = 3  # J^T W r keeps the partial products from GUARD bits below the result's unit
# (fixed.mul_cut); J^T W J from H_GUARD bits below (3 lost GN scenes)
H_GUARD = 5
T_BITS = 12  # the translation's headroom over that binade (module doc: camera points)

_U_COLS = [0, 2, 3, 4, 5]
_V_COLS = [1, 2, 3, 4, 5]
_PAIRS = [(i, k) for i in range(5) for k in range(i, 5)]
# Pair (1, 4) of either row, the (2, 5) entry, is a b c times the weight: minus pair (0, 2)
# of ju and minus pair (0, 3) of jv, so each row computes 14 products (normal.py).
_COMPUTED = [pair for pair in _PAIRS if pair != (1, 4)]
_MIRRORED = (_COMPUTED.index((0, 2)), _COMPUTED.index((0, 3)))
_ORDER = [_COMPUTED.index(p) if p != (1, 4) else len(_COMPUTED) for p in _PAIRS]


def _sources(cols: list[int], entries: list[tuple[int, ...]]) -> list[int | None]:
    """Index into one row's products (pairs, or single columns) for every entry, None
    where the row has a structural zero there."""
    keys = [(cols[i], cols[k]) for i, k in _PAIRS] if len(entries[0]) == 2 else \
        [(c,) for c in cols]
    return [keys.index(e) if e in keys else None for e in entries]


def _gather(fx, terms: TC, n: int, sources: tuple[list, list]) -> TC:
    """(2n, entries): each entry's u-row terms over its v-row terms, zero where a row
    does not touch the entry, so the sum tree's first level adds the two rows."""
    zero = fx.zeros_tc((n,), terms.w)
    rows = [fx.stack_tc([zero if idx is None else fx.index_tc(terms, (slice(None), row, idx))
                         for idx in src], 1) for row, src in enumerate(sources)]
    return fx.concat_tc(rows, 0)


def map_block(world: F) -> tuple[SM, object]:
    """The map as block floating point: W_MAP-bit magnitudes at the scale of its largest
    exponent, and that exponent."""
    fx = fix_backend(world)
    ew = fx.block_emax(world)
    return fx.from_float(world, ew, W_MAP), ew


def map_fixed(world: np.ndarray) -> tuple[np.ndarray, np.uint8]:
    """The ``wmap`` and ``emap`` inputs of the circuit the client solves: map_block of the
    float32 map computed in the clear (the circuit would compute the same integers, for
    ~0.65 k AND per point), the sign in bit W_MAP."""
    pts, ew = map_block(F(MirrorBackend(), np.asarray(world, np.float32)))
    return (pts.m | (pts.s << W_MAP)).astype(np.uint32), np.uint8(ew)


def camera_points_fixed(R: F, t: F, world: F) -> F:
    """camera_points_block of the float32 map (map_block)."""
    return camera_points_block(R, t, *map_block(world))


def camera_points_block(R: F, t: F, pts: SM, ew) -> F:
    """X_c = R X + t (n, 3) as float32, computed in fixed point: the map as block floating
    point (its largest exponent ew, W_MAP bits), R at the public scale 2^-F_ROT, t at the
    map's scale with T_BITS more integer bits (saturating beyond), exact integer sums,
    one rounding to float32 per coordinate.

    Error bound, M the map's largest |coordinate| and v = 2^-(W_MAP - 1) M: the unit of
    the map's magnitudes is at most v, that of the products and of t v / 2 (W_XC), so
    each product R_ij X_j is off by less than v (X truncated: the same for every pose, a
    map moved by less than v) + 2^-F_ROT M = v / 2 (R truncated) + 2.5 v (the product's
    floor and its partial products below 2^-X_GUARD of its unit: 2 x 13 terms /
    2^(X_GUARD + 1) < 4 units), t by less than v / 2: before the final rounding a
    coordinate is within 12.5 v, after it within 12.5 v + 2^-24 |X_c|
    (tests/test_loc_fixed.py). float32 is within a few 2^-24 (M + |t|).
    """
    fx = fix_backend(R)
    rot = fx.from_float(R, SCALE_BIAS + 1, F_ROT + 1)  # magnitudes of 1.0 are 2^F_ROT
    trans = fx.twos(fx.from_float(t, fx.exponent_plus(ew, T_BITS), W_XC + T_BITS))
    drop = F_ROT + W_MAP - W_XC
    prods = fx.mul_cut(rot[None], pts[:, None, :], drop, drop - X_GUARD, W_XC + 1)  # (n, 3, 3)
    rx = fx.sum_tc(fx.stack_tc([fx.index_tc(prods, (slice(None), slice(None), j))
                                for j in range(3)], 0))
    return fx.to_float_scaled(fx.add_tc(rx, fx.index_tc(trans, (None,))), ew, W_XC)


def normal_equations_fixed(R: F, t: F, image: F, block: tuple[SM, object], weights: F,
                           wfix, h_shift: int = 0, r_bits: int = W_R):
    """(hess (21,), grad (6,), cost (), ec, er), all integers: module doc. ``block`` is the
    map as map_block gives it (the client passes it as integers: ``map_fixed``); ``wfix`` is the
    (n, 2) integer square roots of the weights (mirror: int64; circuit: W_W-bit input
    words), which the cost uses too: ``weights`` is not read. J^T W J takes the
    Jacobian's magnitudes ``h_shift`` bits shorter and J^T W r the residuals at
    ``r_bits`` (H_SHIFT and W_RS where the client solves)."""
    xc = camera_points_block(R, t, *block)
    proj = xc[:, 0:2] / xc[:, 2:3]  # a = x/z, b = y/z correctly rounded
    err = proj - image
    fx = fix_backend(R)
    n = len(proj)
    a = fx.from_float(proj[:, 0], EMAX_A, W_A)
    b = fx.from_float(proj[:, 1], EMAX_A, W_A)
    c, ec = fx.recip_block(xc[:, 2], W_C)
    er = fx.block_emax(err)
    rc = fx.from_float(err, er, W_RC)
    sw16 = fx.unsigned(wfix, W_W)                                 # sqrt(w): module doc
    src = fx.mul_cut_sm(rc, sw16, F_W, F_W - GUARD, W_RC)        # < 2^W_RC: sqrt(w) <= 2^F_W
    cost_pt = fx.mul_cut(src, src, D_COST, D_COST - GUARD, 2 * W_RC - D_COST)
    cost = fx.sum_tc(fx.concat_tc([fx.index_tc(cost_pt, (slice(None), k)) for k in range(2)], 0))
    sw = fx.shr(sw16, W_W - W_WS)                                 # (n, 2), 2^(W_WS - 1) is 1
    cw = fx.mul(c[:, None], sw, W_WS - 1, W_C)                    # sqrt(w) c per row
    aw = fx.mul(a[:, None], sw, W_WS - 1, W_A)
    bw = fx.mul(b[:, None], sw, W_WS - 1, W_A)
    ab_pair = fx.stack([a, b], 1)
    cwab = fx.mul(cw, ab_pair, F_A, W_C + 1)                      # sqrt(w) (a c, b c)
    awb = fx.mul(aw, b[:, None], F_A, W_A + 1)                    # sqrt(w) a b
    sq = fx.stack([aw[:, 0], bw[:, 1]], 1)
    one = fx.add_shl(fx.mul(sq, ab_pair, F_A, W_A + 1), sw, F_A - W_WS + 1, W_A + 2)
    ju = fx.stack([cw[:, 0], fx.neg(cwab[:, 0]), fx.neg(awb[:, 0]), one[:, 0], fx.neg(bw[:, 0])], 1)
    jv = fx.stack([cw[:, 1], fx.neg(cwab[:, 1]), fx.neg(one[:, 1]), awb[:, 1], aw[:, 1]], 1)
    jac = fx.stack([ju, jv], 1)                                   # sqrt(w) J (n, 2, 5)
    jh = fx.shr(jac, h_shift)
    pair_w = 2 * jac.w - DROP
    drop_h = DROP - 2 * h_shift
    computed = fx.concat_tc([fx.mul_cut(jh[:, :, i:i + 1], jh[:, :, i:4 if i == 1 else 5],
                                        drop_h, drop_h - H_GUARD, pair_w)
                             for i in range(5)], 2)                    # (n, 2, 14)
    mirrored = fx.neg_tc(fx.stack_tc([fx.index_tc(computed, (slice(None), row, [_MIRRORED[row]]))
                                      for row in range(2)], 1))      # (n, 2, 1)
    hpair = fx.index_tc(fx.concat_tc([computed, mirrored], 2), (slice(None), slice(None), _ORDER))
    entries = [e for e in UPPER if e != (0, 1)]
    hterms = _gather(fx, hpair, n, (_sources(_U_COLS, entries), _sources(_V_COLS, entries)))
    hess = fx.sum_tc(hterms)
    wr = fx.shr(src, W_RC - r_bits)  # sqrt(w) r at r_bits bits: floors compose
    gpart = fx.mul_cut(wr[:, :, None], jac, DROP, DROP - GUARD, jac.w + r_bits - DROP)
    gentries = [(i,) for i in range(6)]
    gterms = _gather(fx, gpart, n, (_sources(_U_COLS, gentries), _sources(_V_COLS, gentries)))
    grad = fx.sum_tc(gterms)
    hess = fx.insert_zero(hess, UPPER.index((0, 1)))               # ju, jv never both
    return hess, grad, cost, ec, er


def _block_scale(emax, width: int) -> float:
    """log2 of the unit of a block's magnitudes (fixed.py: from_float)."""
    return float(int(emax) - width - SCALE_BIAS)


def scales(ec: int, er: int) -> tuple[np.ndarray, float]:
    """log2 of each column's scale (6,) and of the residuals' scale, from the block
    exponents the circuit returned."""
    sc = _block_scale(ec, W_C)
    return np.array([sc, sc, sc, -F_A, -F_A, -F_A], float), _block_scale(er, W_RS)


def weights_fixed(weights: np.ndarray) -> np.ndarray:
    """The ``wfix`` input: the weights normalized to a largest of 2^F_W, rounded."""
    w = np.asarray(weights, np.float64)
    top = weight_unit(w)
    if not top > 0.0:
        return np.zeros(w.shape, np.uint16)
    return np.rint(np.sqrt(w / top) * (1 << F_W)).astype(np.uint16)


def weight_unit(weights: np.ndarray) -> float:
    """What ``weights_fixed`` divided the weights by (relative to 1): the sums and the cost
    times it are in the units of the float circuit."""
    return float(np.max(weights)) if np.size(weights) else 0.0


def decode(weights: np.ndarray, out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The circuit's integer outputs as float64 J^T W J (packed), J^T W r and the cost, in
    the units of the float circuit (weights as given, not normalized)."""
    col, sr = scales(int(out["ec"]), int(out["er"]))
    top = weight_unit(weights)
    rows, cols = np.array(UPPER).T
    hess = np.asarray(out["hess"], np.float64) * np.exp2(col[rows] + col[cols] + DROP) * top
    grad = np.asarray(out["grad"], np.float64) * np.exp2(col + sr + DROP) * top
    cost = float(out["cost"]) * 2.0 ** (D_COST + 2 * _block_scale(out["er"], W_RC)) * top
    return {"hess": hess, "grad": grad, "cost": np.float64(cost)}


def float_system(R: F, hess, grad, cost, ec, er):
    """For a solve inside the circuit: the integer sums as float32 (hess, grad, cost) and
    the function taking the solution y of hess y = -grad to the step in the float
    circuit's units. The solve needs no scales: with H = D H' D and g = s D g' (D the
    column scales), the step is s D^-1 y; only the cost and the step get exponents.
    ``hess`` comes as integers of at most 2^HESS_BITS times 2^-HESS_BITS, so its entries
    are at most 1 and the block solve's cubic terms stay inside float32 even after
    lambda_max damping (block_ldlt.py); the step's exponents undo that factor."""
    fx = fix_backend(R)
    hess_f, drop_h = fx.to_float(hess)
    hess_f = fx.scale2(hess_f, -HESS_BITS)
    grad_f, drop_g = fx.to_float(grad)
    cost_f, drop_k = fx.to_float(cost)
    cost_f = fx.scale2(cost_f, fx.exponent_offset(er, None, drop_k + D_COST - W_RC - SCALE_BIAS))
    cost_f = fx.scale2(cost_f, fx.exponent_offset(er, None, -W_RC - SCALE_BIAS))
    shift = drop_g - drop_h - HESS_BITS
    to_translation = fx.exponent_offset(er, ec, W_C - W_R + shift)        # sr - sc
    to_rotation = fx.exponent_offset(er, None, F_A - W_R - SCALE_BIAS + shift)   # sr + F_A

    def unscale(y: F) -> F:
        return concat([fx.scale2(y[0:3], to_translation), fx.scale2(y[3:6], to_rotation)])

    return hess_f, grad_f, cost_f, unscale
