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
  precision normal.py's narrow floats already had. The Jacobian is that of the step
  (v', w) rotating about the map's origin, R' = exp(w) R, t' = t + v' (types.py's step
  rotates about the camera: v = v' - [t]x w to first order; loc/backends.py turns the
  sums and steps into it in float64). About the camera, the rotation columns (-a b,
  1 + a^2, -b; ...) of a small tag far away are nearly those of a translation: J^T W J's
  scaled eigenvalues went down to 3e-5 on one-tag frames, its fixed-point errors of
  1e-3 made it indefinite, and GN lost a fifth of such frames (the in-circuit solve
  half, its LM crawled to the iteration cap on a quarter); each quantity swapped for
  float64 in the mirror showed it: only J^T W J exact (or J^T J formed without the
  products' floors) saved them. About the map's origin the rotation columns are c times
  R X (u: -a c Y_y, c (Y_z + a Y_x), -c Y_y; v: -c (Y_z + b Y_y), b c Y_x, c Y_x, with
  Y = R X, the exact sum camera_points_rotated keeps, at W_Y bits of the map's binade),
  apart from the translation's, and the smallest scaled eigenvalue of the same frames
  is 1e-2. sqrt(w) multiplies c (2 products per point), and sqrt(w) c multiplies a, b
  (2) and Y (6), a and b those (4): 14 products, the last 10 truncated (fixed.mul_cut_sm,
  GUARD bits; exact ones cost 0.9 k AND per point more and converged no better), the
  translation columns' exact floors. J^T W J = (sqrt(w) J)^T (sqrt(w) J) and J^T W r =
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
  unconverged (seed 2), shift 5 lost two (seed 1); with the rotation about the map's
  origin and its columns' own block exponents, shift 4 (H_SHIFT) loses none of 300
  one-tag, 400 random and 300 plane-tags scenes (shift 5 lost a flat valley's n = 4
  scene). The in-circuit solve shifts by H_SHIFT_SOLVE = 2: with 4 its GN lost 3 of 300
  one-tag scenes and 1 of 300 plane-tags ones, with 2 none (1.2 k AND per point less than
  0; about the camera it had kept all 13 bits, its LM at the 20-iteration cap on 2 of
  1,000 random scenes with a shift). The products of J^T W J and J^T W r are truncated
  (fixed.mul_cut, GUARD and H_GUARD), each row of J^T W J's with one shared multiplicand.
  Each square on J^T W J's diagonal is floored at its unit, half a unit lost on average:
  nothing against a large column, but a weak one (a tag seen head-on: its tilt barely
  moves the corners, a column of 5-8 bits) lost up to a tenth of its diagonal and GN
  crawled to the cap (n = 4 random scenes); the client adds the half units back
  (``decode``), the in-circuit solve adds them rounded (``with_floors``: the live points
  counted from ``wfix``, a few hundred AND in all);
- the client passes the square roots of its weights normalized to a largest weight of 1
  as 16-bit integers (``wfix``, 2^F_W for 1): the cost takes all 16 bits, the Jacobian
  the top W_WS = 10 (a free truncation; sqrt(w) r is the cost's, shortened). The float32
  weights stay an input (unused by this circuit; the client decodes with their largest,
  ``weight_unit``).

Outputs are integers: ``hess`` (21, packed as normal.UPPER) at scale
2^(s_i + s_k + DROP), ``grad`` (6) at 2^(s_i + sr + DROP), where s is the column scale
(translation columns: the inverse depths' block scale sc; rotation columns: sc times
the map's block unit and 2^Y_DROP) and sr
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
W_Y = 13  # R X in the rotation columns, relative to the map's largest binade
Y_DROP = 2  # c R X drops these bits more, so it fits W_C - 1 bits (|R X| < 2^(1/2 + 1))
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
H_SHIFT_SOLVE = 2  # the same for the in-circuit solve (module doc)
H_SHIFT = 4  # J^T W J's Jacobian magnitudes are this much shorter when the client solves
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
    """camera_points_rotated's camera points."""
    return camera_points_rotated(R, t, pts, ew)[0]


def camera_points_rotated(R: F, t: F, pts: SM, ew) -> tuple[F, TC]:
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
    (tests/test_loc_fixed.py). float32 is within a few 2^-24 (M + |t|). Also R X, the
    exact sum before t is added, in units of 2^(ew - W_XC - SCALE_BIAS): the rotated map
    the Jacobian's rotation columns take (normal_equations_fixed).
    """
    fx = fix_backend(R)
    rot = fx.from_float(R, SCALE_BIAS + 1, F_ROT + 1)  # magnitudes of 1.0 are 2^F_ROT
    trans = fx.twos(fx.from_float(t, fx.exponent_plus(ew, T_BITS), W_XC + T_BITS))
    drop = F_ROT + W_MAP - W_XC
    prods = fx.mul_cut(rot[None], pts[:, None, :], drop, drop - X_GUARD, W_XC + 1)  # (n, 3, 3)
    rx = fx.sum_tc(fx.stack_tc([fx.index_tc(prods, (slice(None), slice(None), j))
                                for j in range(3)], 0))
    return fx.to_float_scaled(fx.add_tc(rx, fx.index_tc(trans, (None,))), ew, W_XC), rx


def normal_equations_fixed(R: F, t: F, image: F, block: tuple[SM, object], weights: F,
                           wfix, h_shift: int = 0, r_bits: int = W_R):
    """(hess (21,), grad (6,), cost (), ec, er), all integers: module doc. ``block`` is the
    map as map_block gives it (the client passes it as integers: ``map_fixed``); ``wfix`` is the
    (n, 2) integer square roots of the weights (mirror: int64; circuit: W_W-bit input
    words), which the cost uses too: ``weights`` is not read. J^T W J takes the
    Jacobian's magnitudes ``h_shift`` bits shorter and J^T W r the residuals at
    ``r_bits`` (H_SHIFT and W_RS where the client solves)."""
    xc, rx = camera_points_rotated(R, t, *block)
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
    ab_pair = fx.stack([a, b], 1)
    cwab = fx.mul(cw, ab_pair, F_A, W_C + 1)                      # sqrt(w) (a c, b c)
    y = fx.sm_from_tc(rx, W_XC - W_Y, W_Y + 1)                    # R X (n, 3): module doc
    cwy = fx.mul_cut_sm(cw[:, :, None], y[:, None, :], W_Y + Y_DROP, W_Y + Y_DROP - GUARD,
                        W_C - 1)                                  # sqrt(w) c R X
    abcy = fx.mul_cut_sm(ab_pair[:, :, None], cwy[:, :, 0:2], F_A, F_A - GUARD,
                         W_C)                                     # u: a c Y, v: b c Y (x, y)
    mixed = fx.add_tc(fx.twos(cwy[:, :, 2]), fx.twos(fx.stack([abcy[:, 0, 0], abcy[:, 1, 1]], 1)))
    mixed = fx.sm_from_tc(mixed, 0, W_C + 1)                      # u: c (z + a x), v: c (z + b y)
    ju = fx.stack([cw[:, 0], fx.neg(cwab[:, 0]), fx.neg(abcy[:, 0, 1]), mixed[:, 0],
                   fx.neg(cwy[:, 0, 1])], 1)
    jv = fx.stack([cw[:, 1], fx.neg(cwab[:, 1]), fx.neg(mixed[:, 1]), abcy[:, 1, 0],
                   cwy[:, 1, 0]], 1)
    jac = fx.stack([ju, jv], 1)                                   # sqrt(w) J (n, 2, 5)
    rot, el = fx.normalize_columns(jac[:, :, 2:5])                # each its own block
    jac = fx.stack([jac[:, :, 0], jac[:, :, 1], rot[:, :, 0], rot[:, :, 1], rot[:, :, 2]], 2)
    jh = fx.shr(jac, h_shift)
    pair_w = 2 * jac.w - DROP
    drop_h = DROP - 2 * h_shift
    # every pair of columns of each row: with the rotation columns each at its own scale,
    # pair (1, 4) is no longer minus pair (0, 2) of ju and (0, 3) of jv in units
    hpair = fx.concat_tc([fx.mul_cut(jh[:, :, i:i + 1], jh[:, :, i:5], drop_h,
                                     drop_h - H_GUARD, pair_w) for i in range(5)], 2)
    entries = [e for e in UPPER if e != (0, 1)]
    hterms = _gather(fx, hpair, n, (_sources(_U_COLS, entries), _sources(_V_COLS, entries)))
    hess = fx.sum_tc(hterms)
    wr = fx.shr(src, W_RC - r_bits)  # sqrt(w) r at r_bits bits: floors compose
    gpart = fx.mul_cut(wr[:, :, None], jac, DROP, DROP - GUARD, jac.w + r_bits - DROP)
    gentries = [(i,) for i in range(6)]
    gterms = _gather(fx, gpart, n, (_sources(_U_COLS, gentries), _sources(_V_COLS, gentries)))
    grad = fx.sum_tc(gterms)
    hess = fx.insert_zero(hess, UPPER.index((0, 1)))               # ju, jv never both
    return hess, grad, cost, ec, er, el


def _block_scale(emax, width: int) -> float:
    """log2 of the unit of a block's magnitudes (fixed.py: from_float)."""
    return float(int(emax) - width - SCALE_BIAS)


def scales(ec: int, er: int, emap: int, el: np.ndarray) -> tuple[np.ndarray, float]:
    """log2 of each column's scale (6,) and of the residuals' scale, from the block
    exponents the circuit returned (``el``: the rotation columns' shifts) and the map's
    (the client's ``emap``)."""
    sc = _block_scale(ec, W_C)
    sw = sc + _rotation_shift(emap) - np.asarray(el, float)
    return np.array([sc, sc, sc, *sw], float), _block_scale(er, W_RS)


def _rotation_shift(emap) -> float:
    """log2 of the rotation columns' scale over the translation columns' (c R X against c):
    the unit of R X's W_Y-bit magnitudes, times 2^(W_Y + Y_DROP) that c R X drops."""
    return float(int(emap) - SCALE_BIAS + Y_DROP)


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


def decode(weights: np.ndarray, emap: int, out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The circuit's integer outputs as float64 J^T W J (packed), J^T W r and the cost, in
    the units of the float circuit (weights as given, not normalized), the rotation
    about the map's origin (module doc: the client turns them into types.py's step)."""
    col, sr = scales(int(out["ec"]), int(out["er"]), emap, out["el"])
    top = weight_unit(weights)
    rows, cols = np.array(UPPER).T
    # every square on the diagonal is floored once more at its unit, a loss of half a unit
    # on average: a weak rotation column's few bits (a tag seen head-on: its tilt barely
    # moves the corners) lost up to a tenth of its diagonal so, and GN crawled to the cap
    w = np.asarray(weights) > 0
    counts = np.array([w[:, 0].sum(), w[:, 1].sum()] + [w.sum()] * 4, np.float64)
    floors = np.zeros(len(UPPER))
    floors[[UPPER.index((i, i)) for i in range(6)]] = counts / 2
    hess = (np.asarray(out["hess"], np.float64) + floors) \
        * np.exp2(col[rows] + col[cols] + DROP) * top
    grad = np.asarray(out["grad"], np.float64) * np.exp2(col + sr + DROP) * top
    cost = float(out["cost"]) * 2.0 ** (D_COST + 2 * _block_scale(out["er"], W_RC)) * top
    return {"hess": hess, "grad": grad, "cost": np.float64(cost)}


def with_floors(R: F, hess: TC, wfix) -> TC:
    """J^T W J with the mean loss of its diagonal's floors added back (decode's, for the
    in-circuit solve): half a unit per square of a point with a non-zero weight, rounded
    to whole units; the weights' ``wfix`` words say which are."""
    fx = fix_backend(R)
    live = fx.nonzero(wfix)                                      # (n, 2)
    rows = [fx.sum_tc(fx.index_tc(live, (slice(None), k))) for k in range(2)]
    both = fx.add_tc(rows[0], rows[1])
    halves = [fx.shr_tc(fx.add_tc(count, fx.constant_tc(1, 2)), 1)
              for count in (rows[0], rows[1], both)]
    diag = {UPPER.index((i, i)): halves[min(i, 2)] for i in range(6)}
    entries = [fx.add_tc(fx.index_tc(hess, p), diag[p]) if p in diag else fx.index_tc(hess, p)
               for p in range(len(UPPER))]
    return fx.stack_tc(entries, 0)


def rotation_damping(hess: F, t: F, ew, el) -> F:
    """What rotating about the camera adds to the rotation columns' diagonal, but for the
    cross terms: sum_j ((t x e_k)_j)^2 H_jj (k = x, y, z; j over the translation columns),
    in float_system's units (sil.damped). There the rotation column k's scale over the
    translation columns' is the map's block unit times 2^(Y_DROP - el_k) (``scales``)."""
    fx = fix_backend(t)
    ts = fx.scale2(t, fx.exponent_neg(ew, SCALE_BIAS - Y_DROP))
    diag = hess[[UPPER.index((j, j)) for j in range(3)]]
    # (t x e_k)^2 for k = x, y, z: (0, tz^2, ty^2), (tz^2, 0, tx^2), (ty^2, tx^2, 0)
    moved = (ts * ts)[[2, 1, 2, 0, 1, 0]] * diag[[1, 2, 0, 2, 0, 1]]
    return fx.scale2(moved[0::2] + moved[1::2], fx.exponent_add(None, el, 2))


def float_system(R: F, hess, grad, cost, ec, er, el, ew):
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
    to_rotation = fx.exponent_offset(to_translation, ew, SCALE_BIAS - Y_DROP)

    to_rotation = fx.exponent_add(to_rotation, el)

    def unscale(y: F) -> F:
        return concat([fx.scale2(y[0:3], to_translation), fx.scale2(y[3:6], to_rotation)])

    return hess_f, grad_f, cost_f, unscale
