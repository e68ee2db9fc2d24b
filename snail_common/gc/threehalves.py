"""Three-halves garbling (Rosulek-Roy, CRYPTO 2021, ePrint 2021/749) on blocks of AND gates,
with free-XOR, vectorized with numpy over preallocated buffers like halfgates.py.

A label's two 64-bit words are the scheme's halves: word 0 is the left half (its lowest
bit is the colour, the point-and-permute bit), word 1 the right half. An AND gate costs
three half-words G0, G1, G2 and five control bits z0..z4: 1.5 * 128 + 5 = 197 bits, against
half-gates' 256.

Hash: H(x, t) = AES_k(sigma(x) ^ t) ^ sigma(x), sigma and the word layout as half-gates'.
The scheme uses word 0 of H as a half-label and the lowest bit of word 1 as the mask of a
control bit. AND gate number g hashes its A operand with tweak 3g, B with 3g+1 and A^B with
3g+2, so every AES input of a run is unique.

Evaluation of gate (a, b): the evaluator holds A, B with colours i = lsb(A), j = lsb(B),
hashes hA, hB, hX = H(A), H(B), H(A^B) (halves), with mask bits bA, bB, bX. It decrypts
two control bits ("dicing")
    r1 = z0 ^ i*z2 ^ (i^j)*z4 ^ bA ^ bX        r2 = z1 ^ j*z3 ^ (i^j)*z4 ^ bB ^ bX
which pick the linear map R = r1*S1 ^ r2*S2 ^ P(i, j) it applies to the input halves
("slicing"), and computes the two halves of the output label
    CL = hA ^ hX ^ i*G0 ^ (i^j)*G2 ^ r1*(AL^AR^BL) ^ r2*(AL^BR) ^ (1^i)*BL
    CR = hB ^ hX ^ j*G1 ^ (i^j)*G2 ^ r1*(AL^BR) ^ r2*(AR^BL^BR) ^ (1^j)*AR.
In the paper's terms: V_ij = [[i, 0, i^j], [0, j, i^j]] applied to (G0, G1, G2), the hash
matrix [[1, 0, 1], [0, 1, 1]] applied to (hA, hB, hX), S1 = [[1,1,1,0], [1,0,0,1]],
S2 = [[1,0,0,1], [0,1,1,1]] and P(i, j) = [[0,0,1^i,0], [0,1^j,0,0]] on (AL, AR, BL, BR).

Garbling: with A, B the colour-0 labels (truth values alpha = lsb of the zero-label,
beta likewise; a = 1^alpha, b = 1^beta are the colours of truth 1), the garbler draws two
secret random bits (r0, r1) per gate and gives the evaluator at colours (i, j) the control
bits r_00 = (r0, r1), r_01 = (r0^a^b, r1^a), r_10 = (r0^b, r1^a^b), r_11 = (r0^a, r1^b):
each marginal is uniform whatever (alpha, beta), so R reveals nothing, and for every
(alpha, beta) these four maps make the system below solvable. Writing K_ij for what the
evaluator at (i, j) computes before adding V_ij G, plus t_ij * D (t_ij = (i^alpha)(j^beta),
the truth value of the output), the output zero-label is C0 = K_00 and
    G0 = K_00L ^ K_11L,   G1 = K_00R ^ K_11R,   G2 = K_00L ^ K_01L
(the remaining equations at (0, 1) and (1, 0) hold by the choice of r). The control bits
are solved the same way with the mask bits in place of the hash halves:
    z0 = r0 ^ bA0 ^ bX0, z1 = r1 ^ bB0 ^ bX0, z2 = a ^ bA0 ^ bA1, z3 = b ^ bB0 ^ bB1,
    z4 = a ^ b ^ bX0 ^ bX1
(bA0, bA1: mask bits of the colour-0 and colour-1 labels of A; bX0, bX1 of A^B and
A^B^D). tests/test_gc_threehalves.py checks all of this exhaustively.

The random bits come from AES-CTR under a key only the garbler knows (derived from the
client's seed, which the evaluator never sees), indexed by gate number, so a run is
reproducible from (seed, D, key) like a half-gates run.

Tables of a block of m gates: m G0, then m G1, then m G2 (8 bytes each), then the control
bits, plane by plane (m z0 bits, m z1 bits, ...), packed least significant bit first and
padded with zero bits to a whole number of 64-bit words (so the next block stays aligned).
"""

from __future__ import annotations

import numpy as np
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from snail_common.circuit.slots import Rows, gather_into

from .aes import AesBatch, byte_view
from .stream import CONTROL_BITS, control_words

U64 = np.uint64
_CONTROL_INFO = b"snail three-halves control bits v1"


def control_key(seed: bytes) -> bytes:
    """The garbler's key for its per-gate random bits, derived from the client's seed
    (HKDF-SHA256, its own label: independent of the label PRG keyed by the seed)."""
    return HKDF(algorithm=hashes.SHA256(), length=16, salt=None,
                info=_CONTROL_INFO).derive(bytes(seed))


class _RandomBits:
    """Two secret random bits per gate number: AES-CTR, 64 gates per AES block."""

    def __init__(self, key: bytes, block: int) -> None:
        self._aes = AesBatch(key)
        k = block // 64 + 2
        self._ctr = np.zeros((k, 2), U64)
        self._out = np.empty((k + 1, 2), U64)
        self._cb, self._ob = byte_view(self._ctr), byte_view(self._out)

    def bits(self, g0: int, n: int) -> np.ndarray:
        """(2, n) uint64 0/1: bits r0, r1 of gates g0 .. g0+n-1."""
        k0, k1 = g0 // 64, (g0 + n - 1) // 64 + 1
        k = k1 - k0
        self._ctr[:k, 0] = np.arange(k0, k1, dtype=U64)
        self._aes.encrypt_into(self._cb[: 16 * k], self._ob[: 16 * k + 16])
        bits = np.unpackbits(self._out[:k].view(np.uint8).reshape(-1), bitorder="little")
        start = 2 * (g0 - 64 * k0)
        return bits[start : start + 2 * n].reshape(n, 2).T.astype(U64)


class ThreeHalves:
    """Garbling and evaluation kernels for blocks of up to ``block`` AND gates.

    One instance per run (it holds the AES key and, for the garbler, D and the key of its
    random bits); not thread-safe. Both kernels gather every operand before writing any
    output, so ``out`` may be rows of ``labels`` itself. ``tables`` is the block's flat
    uint64 array of ``stream.table_words(SCHEME_THREE_HALVES, n)`` words.
    """

    def __init__(self, key: bytes, block: int, delta: np.ndarray | None = None,
                 random_key: bytes | None = None) -> None:
        n = self.block = block
        self._aes = AesBatch(key)
        self._lab = np.empty((6 * n, 2), U64)  # labels to hash
        self._x = np.empty((6 * n, 2), U64)  # AES inputs
        self._y = np.empty((6 * n + 1, 2), U64)  # AES outputs, +1 block for the OpenSSL API
        self._xb, self._yb = byte_view(self._x), byte_view(self._y)
        self._tw = np.empty(6 * n, U64)
        self._h = np.empty(6 * n, U64)  # hash halves, one row per hashed label
        self._hb = np.empty(6 * n, U64)  # hash mask bits
        self._q = np.empty((4, n), U64)  # AL, AR, BL, BR
        self._s = np.empty((3, n), U64)  # AL^AR^BL, AL^BR, AR^BL^BR
        self._t = np.empty((4, 2, n), U64)  # (2, n) scratch rows
        ar = np.arange(n, dtype=U64)
        self._ev_tweaks = np.stack([3 * ar, 3 * ar + 1, 3 * ar + 2])  # A, B, A^B
        self._gb_tweaks = np.repeat(self._ev_tweaks, 2, axis=0)  # each for colours 0, 1
        if delta is not None:
            if random_key is None:
                raise ValueError("a garbling kernel needs the key of its random bits")
            d = self._delta = np.asarray(delta, U64).copy()
            self._d = np.tile(d, (n, 1))
            self._dcol = d.reshape(2, 1)
            dl, dr = d[0], d[1]
            # what moving A, B to colour 1 adds to the S1 and S2 rows (c1, c2 below)
            self._c1 = np.array([[dr], [dl ^ dr]], U64)
            self._c2 = np.array([[dl ^ dr], [dl]], U64)
            self._bits = np.empty((9, n), U64)
            self._tv = np.empty((4, n), U64)
            self._rand = _RandomBits(random_key, block)

    def _hash(self, rows: int, pattern: np.ndarray, g0: int) -> tuple[np.ndarray, np.ndarray]:
        """Hash the first ``rows`` labels of _lab with tweaks 3*g0 + pattern: returns the
        halves and mask bits, each (k, n) for the pattern's k rows."""
        lab, x, tw = self._lab[:rows], self._x[:rows], self._tw[:rows]
        k, n = pattern.shape[0], rows // pattern.shape[0]
        np.add(pattern[:, :n], U64(3 * g0), out=tw.reshape(k, n))
        flat, xf = lab.reshape(-1), x.reshape(-1)
        np.bitwise_xor(flat[:-1], flat[1:], out=xf[:-1])  # word 0: x0 ^ x1 (word 1 junk)
        np.bitwise_xor(lab[:, 0], tw, out=x[:, 1])  # word 1: x0 ^ tweak
        self._aes.encrypt_into(self._xb[: 16 * rows], self._yb[: 16 * rows + 16])
        y = self._y[:rows]
        h, hb = self._h[:rows], self._hb[:rows]
        np.bitwise_xor(y[:, 0], x[:, 0], out=h)  # H word 0 = Y0 ^ x0 ^ x1
        np.bitwise_xor(y[:, 1], x[:, 1], out=hb)  # H word 1 = Y1 ^ x0 = Y1 ^ X1 ^ tweak
        np.bitwise_xor(hb, tw, out=hb)
        np.bitwise_and(hb, U64(1), out=hb)
        return h.reshape(k, n), hb.reshape(k, n)

    def _planes(self, a_rows: np.ndarray, b_rows: np.ndarray, n: int) -> tuple[np.ndarray, ...]:
        """Copy the halves of A and B into planes; return (q, s): q = AL, AR, BL, BR and
        s = AL^AR^BL, AL^BR, AR^BL^BR."""
        q, s = self._q[:, :n], self._s[:, :n]
        np.copyto(q[:2], a_rows.T)
        np.copyto(q[2:], b_rows.T)
        np.bitwise_xor(q[0], q[1], out=s[0])
        np.bitwise_xor(s[0], q[2], out=s[0])
        np.bitwise_xor(q[0], q[3], out=s[1])
        np.bitwise_xor(q[1], q[2], out=s[2])
        np.bitwise_xor(s[2], q[3], out=s[2])
        return q, s

    def garble(self, labels: np.ndarray, a: Rows, b: Rows, g0: int, out: np.ndarray,
               tables: np.ndarray) -> None:
        """Garble gates (a[i], b[i]) numbered g0+i: write their tables and their output
        zero-labels into ``out`` (n, 2)."""
        n = len(out)
        lab = self._lab[: 6 * n].reshape(6, n, 2)  # A, A^D, B, B^D, A^B, A^B^D (colour 0)
        gather_into(labels, a, lab[0])
        gather_into(labels, b, lab[2])
        bits, tv = self._bits[:, :n], self._tv[:, :n]
        alpha, beta, a_, b_ = tv  # truth values of the colour-0 labels; colours of truth 1
        np.bitwise_and(lab[0, :, 0], U64(1), out=alpha)
        np.bitwise_and(lab[2, :, 0], U64(1), out=beta)
        d = self._d[:n]
        for k, truth in ((0, alpha), (2, beta)):  # zero-label -> colour-0 label
            np.bitwise_and(d, np.negative(truth)[:, None], out=lab[k + 1])
            np.bitwise_xor(lab[k], lab[k + 1], out=lab[k])
            np.bitwise_xor(lab[k], d, out=lab[k + 1])
        np.bitwise_xor(lab[0], lab[2], out=lab[4])
        np.bitwise_xor(lab[4], d, out=lab[5])
        h, hb = self._hash(6 * n, self._gb_tweaks, g0)
        q, s = self._planes(lab[0], lab[2], n)
        # bits: r0, r1, r0^a, r1^b, r0^a^b, r1^a, then t00, t11, t01 (output truth values)
        np.bitwise_xor(alpha, U64(1), out=a_)
        np.bitwise_xor(beta, U64(1), out=b_)
        bits[0:2] = self._rand.bits(g0, n)
        np.bitwise_xor(bits[0], a_, out=bits[2])
        np.bitwise_xor(bits[1], b_, out=bits[3])
        np.bitwise_xor(bits[2], b_, out=bits[4])
        np.bitwise_xor(bits[1], a_, out=bits[5])
        np.bitwise_and(alpha, beta, out=bits[6])
        np.bitwise_and(a_, b_, out=bits[7])
        np.bitwise_and(alpha, b_, out=bits[8])
        self._control(hb, bits[0:2], tv[2:], tables, n)
        m = np.negative(bits)
        t = self._t[:, :, :n]
        k00, k11 = t[0], t[1]
        # K_00 = [hA0^hX0; hB0^hX0] ^ r0*s1 ^ r1*s2 ^ [BL; AR] ^ t00*D
        np.bitwise_xor(h[[0, 2]], h[4], out=k00)
        self._add_masked(k00, m[0], s[0:2], t[2])
        self._add_masked(k00, m[1], s[1:3], t[2])
        np.bitwise_xor(k00[0], q[2], out=k00[0])
        np.bitwise_xor(k00[1], q[1], out=k00[1])
        np.bitwise_and(m[6], self._dcol, out=t[2])
        np.bitwise_xor(k00, t[2], out=k00)
        # K_11 (labels A^D, B^D) = [hA1^hX0; hB1^hX0] ^ (r0^a)*(s1^c1) ^ (r1^b)*(s2^c2) ^ t11*D
        np.bitwise_xor(h[[1, 3]], h[4], out=k11)
        self._add_masked(k11, m[2], s[0:2], t[2])
        self._add_masked(k11, m[2], self._c1, t[2])
        self._add_masked(k11, m[3], s[1:3], t[2])
        self._add_masked(k11, m[3], self._c2, t[2])
        np.bitwise_and(m[7], self._dcol, out=t[2])
        np.bitwise_xor(k11, t[2], out=k11)
        g = tables[: 3 * n].reshape(3, n)
        np.bitwise_xor(k00, k11, out=g[:2])
        # K_01, left half (labels A, B^D): hA0^hX1 ^ (r0^a^b)*(s1L^DL) ^ (r1^a)*(s2L^DR)
        # ^ BL ^ DL ^ t01*DL; G2 = K_00L ^ K_01L
        dl, dr = self._delta[0], self._delta[1]
        k01, u = t[3, 0], t[3, 1]
        np.bitwise_xor(h[0], h[5], out=k01)
        np.bitwise_xor(s[0], dl, out=u)
        np.bitwise_and(u, m[4], out=u)
        np.bitwise_xor(k01, u, out=k01)
        np.bitwise_xor(s[1], dr, out=u)
        np.bitwise_and(u, m[5], out=u)
        np.bitwise_xor(k01, u, out=k01)
        np.bitwise_xor(k01, q[2], out=k01)
        np.bitwise_and(m[8], dl, out=u)
        np.bitwise_xor(u, dl, out=u)
        np.bitwise_xor(k01, u, out=k01)
        np.bitwise_xor(k00[0], k01, out=g[2])
        np.copyto(out.T, k00)

    @staticmethod
    def _add_masked(acc: np.ndarray, mask: np.ndarray, rows: np.ndarray,
                    tmp: np.ndarray) -> None:
        """acc ^= mask & rows, mask (n,) broadcast over the two rows."""
        np.bitwise_and(rows, mask, out=tmp)
        np.bitwise_xor(acc, tmp, out=acc)

    def _control(self, hb: np.ndarray, r: np.ndarray, ab: np.ndarray, tables: np.ndarray,
                 n: int) -> None:
        """Write the control bits z0..z4 (see the module docstring) into the tables."""
        z = np.empty((CONTROL_BITS, n), np.uint8)
        a, b = ab
        z[0] = r[0] ^ hb[0] ^ hb[4]
        z[1] = r[1] ^ hb[2] ^ hb[4]
        z[2] = a ^ hb[0] ^ hb[1]
        z[3] = b ^ hb[2] ^ hb[3]
        z[4] = a ^ b ^ hb[4] ^ hb[5]
        ctl = tables[3 * n : 3 * n + control_words(n)]
        ctl[-1] = 0  # the padding bits
        packed = np.packbits(z.reshape(-1), bitorder="little")
        ctl.view(np.uint8)[: len(packed)] = packed

    def evaluate(self, labels: np.ndarray, a: Rows, b: Rows, g0: int, out: np.ndarray,
                 tables: np.ndarray) -> None:
        """Evaluate gates (a[i], b[i]) numbered g0+i from their tables; write their active
        output labels into ``out`` (n, 2)."""
        n = len(out)
        lab = self._lab[: 3 * n].reshape(3, n, 2)  # A, B, A^B
        gather_into(labels, a, lab[0])
        gather_into(labels, b, lab[1])
        np.bitwise_xor(lab[0], lab[1], out=lab[2])
        h, hb = self._hash(3 * n, self._ev_tweaks, g0)
        q, s = self._planes(lab[0], lab[1], n)
        t = self._t[:, :, :n]
        ij, r, c, u = t[0], t[1], t[2], t[3]
        np.bitwise_and(q[0::2], U64(1), out=ij)  # colours i, j
        z = np.unpackbits(tables[3 * n : 3 * n + control_words(n)].view(np.uint8),
                          count=CONTROL_BITS * n, bitorder="little").reshape(CONTROL_BITS, n)
        # r = z[0:2] ^ [i; j]*z[2:4] ^ (i^j)*z4 ^ [bA; bB] ^ bX
        np.bitwise_and(ij, z[2:4], out=r)
        np.bitwise_xor(r, z[0:2], out=r)
        x = u[0]
        np.bitwise_xor(ij[0], ij[1], out=x)  # i^j
        np.bitwise_and(x, z[4], out=u[1])
        np.bitwise_xor(r, u[1], out=r)
        np.bitwise_xor(r, hb[0:2], out=r)
        np.bitwise_xor(r, hb[2], out=r)
        np.negative(r, out=r)
        np.negative(ij, out=ij)
        np.negative(x, out=x)
        g = tables[: 3 * n].reshape(3, n)
        # C = [hA; hB] ^ hX ^ [i; j]*[G0; G1] ^ (i^j)*G2 ^ r1*s1 ^ r2*s2 ^ (1^[i; j])*[BL; AR]
        np.bitwise_xor(h[0:2], h[2], out=c)
        np.bitwise_and(g[2], x, out=u[1])
        np.bitwise_xor(c, u[1], out=c)
        np.bitwise_and(g[0:2], ij, out=u)
        np.bitwise_xor(c, u, out=c)
        self._add_masked(c, r[0], s[0:2], u)
        self._add_masked(c, r[1], s[1:3], u)
        np.invert(ij, out=ij)
        np.bitwise_and(q[2:0:-1], ij, out=u)
        np.bitwise_xor(c, u, out=c)
        np.copyto(out.T, c)
