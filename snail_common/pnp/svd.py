"""SVD solver of the paper's kind, written once against fops.F (circuit and mirror).

A circuit cannot branch, so the textbook algorithm is made oblivious: Householder
bidiagonalization A = U B V^T, then a FIXED number of implicit-shift Golub-Kahan QR
sweeps over the whole 6x6 B (2 per singular value by default, as the paper argues). The
convergence tests of LAPACK's bdsqr become selects: negligible superdiagonals are zeroed
(splitting B into blocks, each of which restarts the chase), and the Wilkinson shift comes
from the lowest unreduced block of B^T B. The solution is x = V pinv(B) U^T b with
singular values below REL_TOL * max dropped. U is never formed: its rotations are applied
to b on the fly; V's rotations are kept and applied to the solution vector at the end.

Depth is time here, so each Givens rotation is one chain: y^2 + z^2, sqrt, a zero guard,
then c and s by two parallel divisions, then one multiply and one add level that rotate
every affected entry in a single batch. No trigonometry.
"""

from __future__ import annotations

from .fops import Cond, F, concat, const, stack
from .normal import UPPER, jacobian, residuals

SIL_SWEEPS = 12  # 2 per singular value, as the paper argues
DO_SWEEPS = 30  # the paper's data-oblivious baseline
REL_TOL = 1e-6  # singular values below REL_TOL * max|s| count as zero
SPLIT_TOL = 2.0**-21  # 4 ulp: a superdiagonal this small against its neighbours is zero
_TINY = 2.0**-126  # smallest normal float32: x < _TINY means x == 0 for squares (flush to 0)
_N = 6


def svd_solve(packed: F, rhs: F, sweeps: int = SIL_SWEEPS) -> F:
    """x = pinv(A) rhs for the symmetric 6x6 A given UPPER-packed (21,); rhs (6,).

    A is first scaled by 1 / max|a_ij| (and x back by the same factor): a damped LM
    Hessian reaches 1e17, and the shift's squared eigenvalue estimates would overflow."""
    be = packed.be
    top = _max(_abs(packed))
    inv = top.lt(_TINY).select(1.0 / top, const(be, 1.0))
    scaled = packed * inv
    at = {e: scaled[p] for p, e in enumerate(UPPER)}
    rows = [stack([at[min(i, k), max(i, k)] for k in range(_N)]) for i in range(_N)]
    return _pinv_apply(stack(rows), rhs, sweeps) * inv


def pinv_step(jac: F, res: F, sweeps: int = SIL_SWEEPS) -> F:
    """Gauss-Newton the paper's way: step = -pinv(J) r for J (m, 6), r (m,), m >= 6.
    Unscaled: singular values must stay below ~1e9 (sqrt(W) J is ~1e5 per entry)."""
    return -_pinv_apply(jac, res, sweeps)


def weighted_system(R: F, t: F, image: F, world: F, weights: F) -> tuple[F, F, F]:
    """(sqrt(W) J (2n, 6), sqrt(W) r (2n,), cost ()) at the pose (R, t): the u rows of all
    points first, then the v rows. The cost is r^T W r summed exactly as in
    normal.normal_equations, so it is bit-identical to the LDL^T program's cost."""
    proj, err, c = residuals(R, t, image, world)
    jac = jacobian(proj, c)
    cost_pt = (err * weights) * err
    cost = (cost_pt[:, 0] + cost_pt[:, 1]).sum(0)
    root = weights.sqrt()
    ju = concat([jac[:, 0], err[:, 0:1]], 1) * root[:, 0:1]
    jv = concat([jac[:, 1], err[:, 1:2]], 1) * root[:, 1:2]
    zero = const(R.be, 0.0, (len(err), 1))
    rows_u = concat([ju[:, 0:1], zero, ju[:, 1:5]], 1)
    rows_v = concat([zero, jv[:, 0:5]], 1)
    return concat([rows_u, rows_v]), concat([ju[:, 5], jv[:, 5]]), cost


def _pinv_apply(a: F, b: F, sweeps: int) -> F:
    """pinv(a) b for a (m, 6), m >= 6, b (m,)."""
    m = a.shape[0]
    if a.shape[1:] != (_N,) or m < _N or b.shape != (m,):
        raise ValueError(f"expected a (m, 6) with m >= 6 and b (m,), got {a.shape}, {b.shape}")
    if sweeps < 1:
        raise ValueError(f"sweeps must be positive, got {sweeps}")
    state = _bidiagonalize(a, b)
    for _ in range(sweeps):
        _sweep(state)
    return _solve_diagonal(state)


class _Bidiagonal:
    """B (diagonal d, superdiagonal e) and c = U^T b as Python lists of scalar F, so a
    rotation touches only what it must; V = diag(1, vsub) G_1 G_2 ... with the sweeps'
    right rotations G_i kept as (column, c, s) and applied to the solution vector at the
    end (a few wavefronts deep), instead of to all of V's rows at every rotation."""

    def __init__(self, d: list[F], e: list[F], vsub: F, c: list[F]) -> None:
        self.d, self.e, self.vsub, self.c = d, e, vsub, c
        self.rotations: list[tuple[int, F, F]] = []


def _bidiagonalize(a: F, b: F) -> _Bidiagonal:
    """Householder from the left on columns, from the right on rows; the active block
    shrinks by one row and column per step, and V's trailing 5x5 block collects the right
    reflectors (V[0] = e0 until the sweeps)."""
    be = a.be
    d: list[F] = []
    e: list[F] = []
    c: list[F] = []
    vsub = _identity(be, _N - 1)
    block = concat([a, b[:, None]], 1)  # active rows x (active columns + rhs)
    for k in range(_N):
        if block.shape[0] > 1:
            alpha, rest = _reflect(block[:, 0], block[:, 1:])
        else:
            alpha, rest = block[0, 0], block[:, 1:]
        d.append(alpha)
        c.append(rest[0, -1])
        row = rest[0, :-1]
        below = rest[1:]
        if len(row) > 1:
            cols = concat([below[:, :-1], vsub[:, k:]], 0)
            beta, moved = _reflect(row, _transpose(cols))
            moved = _transpose(moved)
            nb = below.shape[0]
            e.append(beta)
            vsub = concat([vsub[:, :k], moved[nb:]], 1)
            block = concat([moved[:nb], below[:, -1:]], 1)
        else:
            if len(row) == 1:
                e.append(row[0])
            block = below
    return _Bidiagonal(d, e, vsub, c)


def _identity(be, n: int) -> F:
    return stack([stack([const(be, float(i == j)) for j in range(n)]) for i in range(n)])


def _transpose(x: F) -> F:
    return stack([x[:, j] for j in range(x.shape[1])])


def _reflect(x: F, block: F) -> tuple[F, F]:
    """Householder H = I - v v^T / h with H x = alpha e0 (alpha = -sign(x0) |x|, so
    v0 = x0 - alpha never cancels): returns alpha and H block. x^T block is formed while
    |x| is still being computed; a zero x gives H = I instead of 0/0."""
    be = x.be
    s2 = (x * x).sum(0)
    xb = (x[:, None] * block).sum(0)
    neg = x[0].lt(0.0)
    nrm = s2.sqrt()
    alpha = neg.select(-nrm, nrm)
    ax0 = neg.select(x[0], -x[0])
    h = s2.lt(_TINY).select(s2 + ax0 * nrm, const(be, 1.0))  # v^T v / 2 = s2 + |x0| |x|
    w = (xb - block[0] * alpha) * (1.0 / h)  # v^T block / h, one division
    v = concat([(x[0] - alpha)[None], x[1:]])
    return alpha, block - v[:, None] * w[None, :]


def _givens(y: F, z: F) -> tuple[F, F, F]:
    """(c, s, r): r = sqrt(y^2 + z^2), (c, s) = (y, z) / r by two parallel divisions, so
    c y + s z = r and c z - s y = 0; (c, s) = (1, 0) when r is zero."""
    be = y.be
    yz = stack([y, z])
    sq = yz * yz
    q = sq[0] + sq[1]
    zero = q.lt(_TINY)
    one = const(be, 1.0)
    r = q.sqrt()
    cs = stack([zero.select(y, one), z]) / zero.select(r, one)
    return cs[0], cs[1], r


Pair = tuple[F | None, F | None, bool]


def _rotate(c: F, s: F, pairs: list[Pair]) -> list[tuple[F | None, F | None]]:
    """(c x + s y, c y - s x) for each (x, y, both) in one multiply and one add batch;
    None is a structural zero (no gates), and both=False skips the second output (an
    entry the rotation annihilates)."""
    left: list[F] = []
    right: list[F] = []
    plan = []  # per pair: (index terms of x', index terms of y') as (product, sign)

    def prod(v: F, k: F) -> int:
        left.append(v)
        right.append(k)
        return len(left) - 1

    for x, y, both in pairs:
        xs, ys = [], []
        if x is not None:
            xs.append((prod(x, c), 1))
            if both:
                ys.append((prod(x, s), -1))
        if y is not None:
            xs.append((prod(y, s), 1))
            if both:
                ys.append((prod(y, c), 1))
        plan.append((xs, ys))
    if not left:
        return [(None, None) for _ in pairs]
    p = stack(left) * stack(right)
    terms = [p[i] if sign > 0 else -p[i] for i, sign in (t for xs, ys in plan for t in xs + ys)]
    at = 0
    firsts, seconds, slots = [], [], []
    for xs, ys in plan:
        for part in (xs, ys):
            if len(part) == 2:
                firsts.append(terms[at])
                seconds.append(terms[at + 1])
                slots.append(("sum", len(firsts) - 1))
            elif len(part) == 1:
                slots.append(("one", at))
            else:
                slots.append(("none", 0))
            at += len(part)
    sums = stack(firsts) + stack(seconds) if firsts else None
    outs: list[F | None] = []
    for kind, i in slots:
        outs.append(sums[i] if kind == "sum" else terms[i] if kind == "one" else None)
    return [(outs[2 * i], outs[2 * i + 1]) for i in range(len(pairs))]


def _at(cond: Cond, idx) -> Cond:
    """Leading-axis indexing of a condition (fops.Cond has no operators of its own)."""
    return Cond(cond.be, cond.v[idx])


def _abs(x: F) -> F:
    return x.lt(0.0).select(x, -x)


def _max(x: F) -> F:
    """Largest entry of a vector by a tree of compare-selects."""
    while len(x) > 1:
        half = len(x) // 2
        a, b = x[0:2 * half:2], x[1:2 * half:2]
        pairs = a.lt(b).select(a, b)
        x = pairs if len(x) % 2 == 0 else concat([pairs, x[len(x) - 1:]])
    return x[0]


def _shift(d: list[F], e: list[F]) -> F:
    """Wilkinson shift of the lowest unreduced block of T = B^T B (coupling d_j e_j not
    negligible against T_jj + T_j+1,j+1): the eigenvalue of its trailing 2x2 nearer the
    last diagonal entry, mu = a22 - sign(delta) a12^2 / (|delta| + sqrt(delta^2 + a12^2)).
    T, not B: a zero d_j splits T while e_j stays, and a shift from below such a split
    would target a singular value that has already converged."""
    be = d[0].be
    p = stack(d + e + d[:_N - 1]) * stack(d + e + e)
    dd, ee, de = p[0:_N], p[_N:2 * _N - 1], p[2 * _N - 1:]
    tdiag = concat([dd[0:1], dd[1:] + ee])
    coupled = ((tdiag[0:_N - 1] + tdiag[1:]) * SPLIT_TOL).lt(_abs(de))
    pick = stack([tdiag[0], tdiag[1], de[0]])
    for j in range(1, _N - 1):
        pick = _at(coupled, j).select(pick, stack([tdiag[j], tdiag[j + 1], de[j]]))
    a11, a22, a12 = pick[0], pick[1], pick[2]
    delta = (a11 - a22) * 0.5
    sq = stack([delta, a12]) * stack([delta, a12])
    disc = (sq[0] + sq[1]).sqrt()
    neg = delta.lt(0.0)
    den = _abs(delta) + disc
    den = den.lt(_TINY).select(den, const(be, 1.0))
    return a22 + neg.select(-sq[1], sq[1]) / den


def _sweep(st: _Bidiagonal) -> None:
    """One implicit-shift Golub-Kahan sweep, chasing the bulge down with alternating right
    (columns, also V) and left (rows, also U^T b) rotations.

    Oblivious deflation: a superdiagonal below SPLIT_TOL times its neighbours is set to 0,
    which splits B into blocks. The rotation at a split is forced to the exact identity
    and the block below restarts with its own implicit first rotation, from values known
    when the sweep starts (the identity, and a left rotation by c = +-1 that keeps d_k^2
    and d_k e_k, leave them unchanged). Without restarts, a block cut off early by a
    fast-converging split is never touched again."""
    d, e, cb = st.d, st.e, st.c
    be = d[0].be
    mag = _abs(stack(d + e))
    coupled = ((mag[0:_N - 1] + mag[1:_N]) * SPLIT_TOL).lt(mag[_N:])
    ev = coupled.select(const(be, 0.0, (_N - 1,)), stack(e))
    e[:] = [ev[j] for j in range(_N - 1)]
    mu = _shift(d, e)
    first = stack(d[:_N - 1] * 2) * stack([*d[:_N - 1], *e])  # d_k^2 and d_k e_k
    start = stack([first[0:_N - 1] - mu, first[_N - 1:]], 1)
    idle = stack([const(be, 1.0, (_N - 1,)), const(be, 0.0, (_N - 1,))], 1)
    alt = _at(coupled, (slice(None), None)).select(idle, start)  # (1, 0): exact identity
    # the chase goes on through k only where k-1 and k are both coupled; elsewhere k
    # restarts (or idles): one select on the dependency chain
    ones = coupled.select(const(be, 0.0, (_N - 1,)), const(be, 1.0, (_N - 1,)))
    restart = (ones[0:_N - 2] * ones[1:]).lt(0.5)
    bulge: F | None = None  # B[k-1, k+1], left behind by the previous left rotation
    for k in range(_N - 1):
        if bulge is None:
            y, z = alt[k, 0], alt[k, 1]
        else:
            yz = _at(restart, k - 1).select(stack([e[k - 1], bulge]), alt[k])
            y, z = yz[0], yz[1]
        c, s, r = _givens(y, z)
        if bulge is not None:  # a chase annihilates the bulge into r; else bulge = 0
            e[k - 1] = _at(restart, k - 1).select(r, e[k - 1])
        out = _rotate(c, s, [(d[k], e[k], True), (None, d[k + 1], True)])
        (d[k], e[k]), (below, d[k + 1]) = out[0], out[1]
        st.rotations.append((k, c, s))
        c, s, d[k] = _givens(d[k], below)
        pairs: list[Pair] = [(e[k], d[k + 1], True), (cb[k], cb[k + 1], True)]
        if k + 1 < _N - 1:
            pairs.append((None, e[k + 1], True))
        out = _rotate(c, s, pairs)
        (e[k], d[k + 1]), (cb[k], cb[k + 1]) = out[0], out[1]
        bulge = out[2][0] if k + 1 < _N - 1 else None
        if bulge is not None:
            e[k + 1] = out[2][1]


def _solve_diagonal(st: _Bidiagonal) -> F:
    """x = V pinv(B) c once T = B^T B is diagonal: then B's columns are orthogonal with
    norms^2 t_j = d_j^2 + e_j-1^2, so pinv(B) c = diag(1/t) B^T c, dropping t_j <=
    REL_TOL^2 max t. (With e = 0 this is the usual c_j / d_j; it also covers a zero d_j
    whose e_j has not been chased out.)"""
    be = st.d[0].be
    d, e, c = st.d, st.e, st.c
    p = stack(d + e + d + e) * stack(d + e + c + c[:_N - 1])
    t = concat([p[0:1], p[1:_N] + p[_N:2 * _N - 1]])
    btc = concat([p[2 * _N - 1:2 * _N], p[2 * _N:3 * _N - 1] + p[3 * _N - 1:]])
    keep = (_max(t) * (REL_TOL * REL_TOL)).lt(t)  # strict, so an all-zero B gives x = 0
    yv = keep.select(const(be, 0.0, (_N,)), btc / t)
    y = [yv[i] for i in range(_N)]
    for k, cr, sr in reversed(st.rotations):  # y <- G y, G = [[c, -s], [s, c]] on (k, k+1)
        y[k], y[k + 1] = _rotate(cr, -sr, [(y[k], y[k + 1], True)])[0]
    tail = (st.vsub * stack(y[1:])[None, :]).sum(1)
    return concat([y[0][None], tail])
