"""Half-gates on L lanes at once: concurrent runs of one schedule, each lane with its own
AES key, offset D and labels (see lanes.py for why).

A lane's label is words 2l, 2l+1 of a slot's row (W = 2L); inside the kernel everything
is lane-major, (L, rows, 2), so each lane's AES input is one contiguous buffer and its
tables one contiguous block. The math is HalfGates' (halfgates.py documents it) with a
leading lane axis; the one-run kernel keeps its own 2-D buffers because numpy's fixed cost
per call grows with the indexing (a generic kernel measured 7-10 % slower on one lane).
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit.slots import Rows, gather_into

from .aes import AesBatch, byte_view
from .halfgates import U64, sigma


class LaneHalfGates:
    """Half-gates kernels for blocks of up to ``block`` AND gates on L lanes, one per AES
    key in ``keys`` (and, garbling, one offset per lane in ``deltas``), lane-major inside.

    Tables are (L, 2n, 2) per block. One instance per pass; not thread-safe; every operand
    is gathered before any output is written, as in HalfGates.
    """

    def __init__(self, keys: list[bytes], block: int,
                 deltas: np.ndarray | None = None) -> None:
        n, lanes = self.block, self.lanes = block, len(keys)
        lead = self._lead = (lanes,)
        self._aes = [AesBatch(key) for key in keys]
        self._ab = np.empty((*lead, 2 * n, 2), U64)  # gathered [A; B] labels, lane-major
        self._rows = np.empty((2 * n, 2 * lanes), U64)
        self._x = np.empty((*lead, 4 * n, 2), U64)  # AES inputs
        self._y = np.empty((*lead, 4 * n + 1, 2), U64)  # +1 block for the OpenSSL API
        self._xb = [byte_view(x) for x in self._x]
        self._yb = [byte_view(y) for y in self._y]
        self._tw = np.empty(2 * n, U64)
        self._lsb = np.zeros((*lead, 4 * n + 1), U64)  # word 0 stays 0: shifts read it
        self._m = np.empty((*lead, 2 * n, 2), U64)  # select masks
        self._u = np.empty((*lead, 2 * n, 2), U64)
        ar = np.arange(n, dtype=U64)
        self._tweak_pattern = np.stack([2 * ar, 2 * ar + 1])  # (2, n): A-half, B-half
        self._lsb_pattern = np.tile(np.array([1, 0], U64), 2 * n)
        # constants tiled to full rows: broadcasting a (2,) row would make numpy's inner
        # loop two words long
        self._k01 = np.tile(np.array([0, 1], U64), (n, 1))  # the (0, 1) tweak residue
        if deltas is not None:
            d = np.asarray(deltas, U64).reshape(*lead, 1, 2)
            self._d = np.repeat(d, n, axis=-2)
            self._sd = np.repeat(sigma(d), 2 * n, axis=-2)

    def _gather_hash_inputs(self, labels: np.ndarray, a: Rows, b: Rows, g0: int,
                            n: int) -> tuple[np.ndarray, np.ndarray]:
        """Gather [A; B] lane-major and write sigma(label) ^ (0, tweak) for each into the
        AES input."""
        ab, x = self._ab[..., : 2 * n, :], self._x[..., : 2 * n, :]
        rows = self._rows[: 2 * n]
        gather_into(labels, a, rows[:n])
        gather_into(labels, b, rows[n:])
        np.copyto(ab, rows.reshape(2 * n, self.lanes, 2).transpose(1, 0, 2))
        tw = self._tw[: 2 * n]
        np.add(self._tweak_pattern[:, :n], U64(2 * g0), out=tw.reshape(2, n))
        # word 0: x0 ^ x1, as one contiguous pass over each lane's flat words (odd
        # positions get junk); word 1: x0 ^ tweak, a strided pass that overwrites the junk
        flat, xf = ab.reshape(*self._lead, -1), x.reshape(*self._lead, -1)
        np.bitwise_xor(flat[..., :-1], flat[..., 1:], out=xf[..., :-1])
        np.bitwise_xor(ab[..., 0], tw, out=x[..., 1])
        return ab, x

    def _masks(self, ab: np.ndarray) -> np.ndarray:
        """All-ones where lsb(label word 0) is 1, per label (both words), lane-major.

        Works on each lane's flat words so every pass is contiguous: keep the lsb of word
        0 (after a leading zero word), copy it onto word 1 by a one-word shift, negate."""
        flat = ab.reshape(*self._lead, -1)
        w = flat.shape[-1]
        lsb = self._lsb[..., : w + 1]
        np.bitwise_and(flat, self._lsb_pattern[:w], out=lsb[..., 1:])
        m = self._m[..., : w // 2, :]
        mf = m.reshape(*self._lead, -1)
        np.bitwise_or(lsb[..., 1:], lsb[..., :-1], out=mf)
        np.negative(mf, out=mf)
        return m

    def _encrypt(self, n_blocks: int) -> None:
        """AES of each lane's first ``n_blocks`` inputs, under that lane's key."""
        size = 16 * n_blocks
        for aes, xb, yb in zip(self._aes, self._xb, self._yb):
            aes.encrypt_into(xb[:size], yb[: size + 16])

    def _lane_major(self, rows: np.ndarray) -> np.ndarray:
        """(n, 2L) output rows as a lane-major (L, n, 2) view (no copy)."""
        return rows.reshape(len(rows), self.lanes, 2).transpose(1, 0, 2)

    def garble(self, labels: np.ndarray, a: Rows, b: Rows, g0: int, out: np.ndarray,
               tables: np.ndarray) -> None:
        """Garble gates (a[i], b[i]) numbered g0+i: write their tables, [TG; TE] per lane,
        and their output zero-labels into ``out`` (n, 2L)."""
        n = len(out)
        ab, x0 = self._gather_hash_inputs(labels, a, b, g0, n)
        x1 = self._x[..., 2 * n : 4 * n, :]
        sd = self._sd[..., : 2 * n, :]
        np.bitwise_xor(x0, sd, out=x1)  # inputs for A0^D, B0^D
        self._encrypt(4 * n)
        y0, y1 = self._y[..., : 2 * n, :], self._y[..., 2 * n : 4 * n, :]
        t = tables
        np.bitwise_xor(y0, y1, out=t)
        np.bitwise_xor(t, sd, out=t)  # [H(A0)^H(A1); H(B0)^H(B1)]
        m = self._masks(ab)
        u = self._u[..., :n, :]
        np.bitwise_and(self._d[..., :n, :], m[..., n:, :], out=u)
        np.bitwise_xor(t[..., :n, :], u, out=t[..., :n, :])  # TG
        u = self._u[..., : 2 * n, :]
        np.bitwise_and(t, m, out=u)  # [pa*TG; pb*(TE^A0)]
        np.bitwise_xor(y0, x0, out=y0)
        np.bitwise_xor(y0, u, out=y0)
        c = self._lane_major(out)
        np.bitwise_xor(y0[..., :n, :], y0[..., n:, :], out=c)
        np.bitwise_xor(c, self._k01[:n], out=c)
        np.bitwise_xor(t[..., n:, :], ab[..., :n, :], out=t[..., n:, :])  # TE

    def evaluate(self, labels: np.ndarray, a: Rows, b: Rows, g0: int, out: np.ndarray,
                 tables: np.ndarray) -> None:
        """Evaluate gates (a[i], b[i]) numbered g0+i from their tables [TG; TE] per lane;
        write their active output labels into ``out`` (n, 2L)."""
        n = len(out)
        ab, x = self._gather_hash_inputs(labels, a, b, g0, n)
        self._encrypt(2 * n)
        y = self._y[..., : 2 * n, :]
        np.bitwise_xor(y, x, out=y)
        m = self._masks(ab)
        u = self._u[..., : 2 * n, :]
        np.bitwise_and(tables, m, out=u)
        np.bitwise_xor(y, u, out=y)  # [H(A)^sa*TG; H(B)^sb*TE]
        c = self._lane_major(out)
        np.bitwise_xor(y[..., :n, :], y[..., n:, :], out=c)
        u = self._u[..., :n, :]
        np.bitwise_and(ab[..., :n, :], m[..., n:, :], out=u)  # sb*A
        np.bitwise_xor(c, u, out=c)
        np.bitwise_xor(c, self._k01[:n], out=c)
