"""Half-gates (Zahur-Rosulek-Evans 2015) on blocks of AND gates, with free-XOR and
point-and-permute, vectorized with numpy over preallocated scratch buffers.

Hash: H(x, i) = AES_k(sigma(x) ^ i) ^ sigma(x), sigma(x0, x1) = (x0 ^ x1, x0) on the two
64-bit words of a label (word 0 is the low word, the label's "left" half); the tweak i sits
in word 1. AND gate number g (global index in the schedule) uses tweak 2g for its generator
half and 2g+1 for its evaluator half, so every AES input of a run is unique.

For gate (a, b) with zero-labels A0, B0, select bits pa = lsb(A0), pb = lsb(B0):
    TG = H(A0, 2g) ^ H(A0^D, 2g) ^ pb*D          TE = H(B0, 2g+1) ^ H(B0^D, 2g+1) ^ A0
    C0 = H(A0, 2g) ^ pa*TG ^ H(B0, 2g+1) ^ pb*(TE ^ A0)
and the evaluator, holding A, B with sa = lsb(A), sb = lsb(B), computes
    C  = H(A, 2g) ^ sa*TG ^ H(B, 2g+1) ^ sb*(TE ^ A).

Layout: a block of n gates is processed as 2n labels [A-half rows; B-half rows], which is
also the order of the tables in the stream (n TG, then n TE), so every per-label operation
is one contiguous numpy call. Identities used to save passes:
- AES output Y of (sigma(x) ^ i) gives H(x, i) = Y ^ X ^ (0, i) with X the AES input; the
  two tweak terms of one gate cancel to (0, 1) in C, added once per gate;
- H(x, i) ^ H(x ^ D, i) = Y0 ^ Y1 ^ sigma(D), since sigma is linear.
Selections by a point-and-permute bit are ANDs with an all-ones/zero mask per label.
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit.slots import Rows, gather_into

from .aes import AesBatch, byte_view

U64 = np.uint64


def sigma(label: np.ndarray) -> np.ndarray:
    """sigma(x0, x1) = (x0 ^ x1, x0) on labels of shape (..., 2)."""
    x = np.asarray(label, dtype=U64)
    return np.stack([x[..., 0] ^ x[..., 1], x[..., 0]], axis=-1)


class HalfGates:
    """Garbling and evaluation kernels for blocks of up to ``block`` AND gates.

    One instance per run (it holds the AES key and, for the garbler, D); not thread-safe.
    Both kernels gather every operand before writing any output, so ``out`` may be rows of
    ``labels`` itself (the plan writes outputs in place when that is safe).
    """

    def __init__(self, key: bytes, block: int, delta: np.ndarray | None = None) -> None:
        n = self.block = block
        self._aes = AesBatch(key)
        self._ab = np.empty((2 * n, 2), U64)  # gathered [A; B] labels
        self._x = np.empty((4 * n, 2), U64)  # AES inputs
        self._y = np.empty((4 * n + 1, 2), U64)  # AES outputs, +1 block for the OpenSSL API
        self._xb, self._yb = byte_view(self._x), byte_view(self._y)
        self._tw = np.empty(2 * n, U64)
        self._lsb = np.zeros(4 * n + 1, U64)  # word 0 stays 0: the shift below reads it
        self._m = np.empty((2 * n, 2), U64)  # select masks
        self._u = np.empty((2 * n, 2), U64)
        ar = np.arange(n, dtype=U64)
        self._tweak_pattern = np.stack([2 * ar, 2 * ar + 1])  # (2, n): A-half, B-half
        self._lsb_pattern = np.tile(np.array([1, 0], U64), 2 * n)
        self._k01 = np.tile(np.array([0, 1], U64), (n, 1))  # the (0, 1) tweak residue
        if delta is not None:
            self._d = np.tile(np.asarray(delta, U64), (n, 1))
            self._sd = np.tile(sigma(delta), (2 * n, 1))

    def _gather_hash_inputs(self, labels: np.ndarray, a: Rows, b: Rows, g0: int,
                            n: int) -> tuple[np.ndarray, np.ndarray]:
        """Gather [A; B] and write sigma(label) ^ (0, tweak) for each into the AES input."""
        ab, x = self._ab[: 2 * n], self._x[: 2 * n]
        gather_into(labels, a, ab[:n])
        gather_into(labels, b, ab[n:])
        tw = self._tw[: 2 * n]
        np.add(self._tweak_pattern[:, :n], U64(2 * g0), out=tw.reshape(2, n))
        # word 0: x0 ^ x1, as one contiguous pass over the flat words (odd positions get
        # junk); word 1: x0 ^ tweak, a strided pass that overwrites the junk
        flat, xf = ab.reshape(-1), x.reshape(-1)
        np.bitwise_xor(flat[:-1], flat[1:], out=xf[:-1])
        np.bitwise_xor(ab[:, 0], tw, out=x[:, 1])
        return ab, x

    def _masks(self, ab: np.ndarray) -> np.ndarray:
        """All-ones where lsb(label word 0) is 1, per label (both words), as (2n, 2).

        Works on the flat word array so every pass is contiguous: keep the lsb of word 0
        (after a leading zero word), copy it onto word 1 by a one-word shift, negate."""
        flat = ab.reshape(-1)
        w = flat.size
        lsb = self._lsb[: w + 1]
        np.bitwise_and(flat, self._lsb_pattern[:w], out=lsb[1:])
        m = self._m[: w // 2]
        mf = m.reshape(-1)
        np.bitwise_or(lsb[1:], lsb[:-1], out=mf)
        np.negative(mf, out=mf)
        return m

    def garble(self, labels: np.ndarray, a: Rows, b: Rows, g0: int, out: np.ndarray,
               tables: np.ndarray) -> None:
        """Garble gates (a[i], b[i]) numbered g0+i: write their tables, [TG; TE] as a
        (2n, 2) array, and their output zero-labels into ``out`` (n, 2)."""
        n = len(out)
        ab, x0 = self._gather_hash_inputs(labels, a, b, g0, n)
        x1 = self._x[2 * n : 4 * n]
        sd = self._sd[: 2 * n]
        np.bitwise_xor(x0, sd, out=x1)  # inputs for A0^D, B0^D
        self._aes.encrypt_into(self._xb[: 64 * n], self._yb[: 64 * n + 16])
        y0, y1 = self._y[: 2 * n], self._y[2 * n : 4 * n]
        t = tables
        np.bitwise_xor(y0, y1, out=t)
        np.bitwise_xor(t, sd, out=t)  # [H(A0)^H(A1); H(B0)^H(B1)]
        m = self._masks(ab)
        u = self._u[:n]
        np.bitwise_and(self._d[:n], m[n:], out=u)
        np.bitwise_xor(t[:n], u, out=t[:n])  # TG
        u = self._u[: 2 * n]
        np.bitwise_and(t, m, out=u)  # [pa*TG; pb*(TE^A0)]
        np.bitwise_xor(y0, x0, out=y0)
        np.bitwise_xor(y0, u, out=y0)
        np.bitwise_xor(y0[:n], y0[n:], out=out)
        np.bitwise_xor(out, self._k01[:n], out=out)
        np.bitwise_xor(t[n:], ab[:n], out=t[n:])  # TE

    def evaluate(self, labels: np.ndarray, a: Rows, b: Rows, g0: int, out: np.ndarray,
                 tables: np.ndarray) -> None:
        """Evaluate gates (a[i], b[i]) numbered g0+i from their tables [TG; TE] (2n, 2);
        write their active output labels into ``out`` (n, 2)."""
        n = len(out)
        ab, x = self._gather_hash_inputs(labels, a, b, g0, n)
        self._aes.encrypt_into(self._xb[: 32 * n], self._yb[: 32 * n + 16])
        y = self._y[: 2 * n]
        np.bitwise_xor(y, x, out=y)
        m = self._masks(ab)
        u = self._u[: 2 * n]
        np.bitwise_and(tables, m, out=u)
        np.bitwise_xor(y, u, out=y)  # [H(A)^sa*TG; H(B)^sb*TE]
        np.bitwise_xor(y[:n], y[n:], out=out)
        u = self._u[:n]
        np.bitwise_and(ab[:n], m[n:], out=u)  # sb*A
        np.bitwise_xor(out, u, out=out)
        np.bitwise_xor(out, self._k01[:n], out=out)
