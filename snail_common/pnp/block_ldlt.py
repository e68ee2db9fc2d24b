"""Block LDL^T solve of a symmetric 6x6 system with 3x3 blocks, for a short chain.

With H = [A B; B^T C], the block factorization H = [I 0; B^T A^-1 I] [A 0; 0 S] [I A^-1 B;
0 I], S = C - B^T A^-1 B, gives the solution of H x = g as
    x2 = S^-1 (g2 - B^T A^-1 g1),    x1 = A^-1 g1 - (A^-1 B) x2.
Both 3x3 inverses are adjugates over determinants, so two divisions replace the six
pivots of ldlt.py, and only 1/det S lies on the dependency chain; the rest are products
and 3-term sums that run side by side. The Schur complement is formed as
det A S = det A C - B^T adj(A) B and brought back to the size of S by det A's power of
two (an exponent subtraction), not by 1/det A, which only A^-1 B and A^-1 g1 wait for;
det S x1 is formed while 1/det S is computed. Nothing pivots: H is a damped (or positive
definite) normal matrix, so A and S are positive definite.

The adjugates and determinants are cubic in the entries: the caller keeps the entries
small enough (normal_fixed.float_system: at most 1, so even lambda_max damping stays far
inside float32). +, - and * run at SOLVE_FRAC fraction bits: the step only steers the
iteration (the LM loop accepts or rejects it on the float32 cost, and the converged pose
is where J^T W r = 0, which the solve does not touch), and the sums entering the solve
carry about 13 significant bits anyway (normal_fixed.py).
"""

from __future__ import annotations

from .fixed import fix_backend
from .fops import F, concat, const
from .normal import UPPER

SOLVE_FRAC = 16  # fraction bits of the solve's +, - and * (module doc)

_AT = {e: p for p, e in enumerate(UPPER)}
_SYM = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]  # a symmetric 3x3, packed
_SYM_AT = {**{e: p for p, e in enumerate(_SYM)}, **{e[::-1]: p for p, e in enumerate(_SYM)}}
# adjugate of a symmetric 3x3 s, entry (i, k) = s[p] s[q] - s[u] s[v], in _SYM order
_ADJ = [((1, 1), (2, 2), (1, 2), (1, 2)), ((0, 2), (1, 2), (0, 1), (2, 2)),
        ((0, 1), (1, 2), (0, 2), (1, 1)), ((0, 0), (2, 2), (0, 2), (0, 2)),
        ((0, 1), (0, 2), (0, 0), (1, 2)), ((0, 0), (1, 1), (0, 1), (0, 1))]


def _adjugate(s: F) -> F:
    """The adjugate (6,) of the symmetric 3x3 ``s`` (6,), both packed as _SYM: one batched
    multiply and one batched subtract."""
    idx = [_SYM_AT[e] for entry in _ADJ for e in entry]
    prods = s[idx[0::2]] * s[idx[1::2]]
    return prods[0::2] - prods[1::2]


def _dots(x: F, y: F, pairs: list[tuple[list[int], list[int]]]) -> F:
    """sum_k x[i_k] y[j_k] over three terms per entry ((i0, i1, i2), (j0, j1, j2)): one
    batched multiply, two batched adds."""
    left = [i for ii, _ in pairs for i in ii]
    right = [j for _, jj in pairs for j in jj]
    prods = x[left] * y[right]
    return (prods[0::3] + prods[1::3]) + prods[2::3]


def _sym_row(i: int) -> list[int]:
    """Indices into a _SYM-packed 3x3 of row (= column) i."""
    return [_SYM_AT[i, k] for k in range(3)]


def _unit_scaled(x: F, d: F) -> F:
    """x / 2^e for e the binary exponent of d: x / d up to a factor in [1, 2), exact and a
    few gates, where x d^k would leave float32's range."""
    fx = fix_backend(x)
    one = const(x.be, 1.0)
    return fx.scale2(x, fx.exponent_offset(fx.block_emax(one), fx.block_emax(d), 0))


def block_ldlt_solve(packed: F, rhs: F) -> F:
    """x with H x = rhs, for H given as its UPPER-packed (21,) entries; rhs (6,)."""
    a = packed[[_AT[e] for e in _SYM]]
    c = packed[[_AT[3 + i, 3 + k] for i, k in _SYM]]
    # columns of [B | g1] (3 x 4), stored column by column, and g2
    bg = concat([packed[[_AT[i, 3 + j] for i in range(3)]] for j in range(3)] + [rhs[0:3]])
    col = [list(range(3 * j, 3 * j + 3)) for j in range(4)]
    with packed.be.narrow(SOLVE_FRAC):
        adj_a = _adjugate(a)
        # adj(A) [B | g1] = det A [A^-1 B | A^-1 g1]; and det A = A[0] . adj(A)[0]
        pool = concat([adj_a, bg, a])
        off_bg, off_a = len(adj_a), len(adj_a) + len(bg)
        pairs = [(_sym_row(i), [off_bg + q for q in col[j]])
                 for j in range(4) for i in range(3)]
        pairs.append((_sym_row(0), [off_a + q for q in _sym_row(0)]))
        m = _dots(pool, pool, pairs)            # (13,): adj(A) [B | g1] by columns, det A
        recip = 1.0 / m[12]
        # B^T adj(A) [B | g1]: the symmetric 3x3 part and B^T adj(A) g1
        pool = concat([bg, m[0:12]])
        off_m = len(bg)
        pairs = [(col[i], [off_m + q for q in col[k]]) for i, k in _SYM]
        pairs += [(col[i], [off_m + q for q in col[3]]) for i in range(3)]
        t = _dots(pool, pool, pairs)            # (9,)
        # det A [S | h] = det A [C | g2] - B^T adj(A) [B | g1], with no wait for 1/det A
        s_h = _unit_scaled(concat([c, rhs[3:6]]) * m[12] - t, m[12])
        p_u = m[0:12] * recip                   # A^-1 B by columns, A^-1 g1
        adj_s = _adjugate(s_h[0:6])
        pool = concat([adj_s, s_h])
        off_s = len(adj_s)
        pairs = [(_sym_row(i), [off_s + 6 + k for k in range(3)]) for i in range(3)]
        pairs.append((_sym_row(0), [off_s + q for q in _sym_row(0)]))
        z = _dots(pool, pool, pairs)            # adj(S) h = det S x2 (3,), det S
        recip_s = 1.0 / z[3]
        # det S x1 = det S A^-1 g1 - (A^-1 B) adj(S) h, formed while 1/det S is computed;
        # row i: (det S u_i - P[i,0] z_0) - (P[i,1] z_1 + P[i,2] z_2)
        q = p_u[[3 * j + i for i in range(3) for j in range(3)] + [9, 10, 11]] * \
            z[[0, 1, 2] * 3 + [3, 3, 3]]
        x1 = (q[9:12] - q[0:9:3]) - (q[1:9:3] + q[2:9:3])
        return concat([x1, z[0:3]]) * recip_s
