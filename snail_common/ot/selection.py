"""Oblivious selection of one-time-padded values: n queries, each a 1-out-of-N OT
(Naor-Pinkas 1999) built from ceil(log2 N) random 1-out-of-2 OTs of an IKNP session.

For the map-owner setting (docs/map-owner.md): the device (receiver) holds n
secret indices into the map owner's N points (positions in its sorted id list); the map
owner (sender) holds the points and a fresh pad P_i per query. The device gets
v[idx_i] ^ P_i and nothing else; the map owner sees only OT choice bits under IKNP's pads.
No garbled circuit: n N width bytes from the map owner and n ceil(log2 N) OTs.

Per query i the sender holds l key pairs (K_ij^0, K_ij^1) from random OT, and entry k of
table i is  e_ik = (v_k ^ P_i) ^ XOR_j F(K_ij^{bit j of k}, (i l + j) N + k),
F being the fixed-key AES hash of ``blocks.py`` under a fresh public key per table. The
receiver holds K_ij^{bit j of idx_i} only, so every other entry has a term it cannot
compute. k is in the tweak: without it the XOR of four entries would cancel the pads.

Messages: receiver -> sender ``ot_ext_u`` (the index bits, l per query, low bit first);
sender -> receiver ``sel_table`` {start, key, table}.
"""

from __future__ import annotations

import secrets

import numpy as np

from ..net.errors import BAD_REQUEST, UNEXPECTED, ProtocolError
from . import wire
from .blocks import CorrelationRobustHash
from .iknp import ExtReceiver, ExtSender

MAX_TABLE_BYTES = 1 << 28  # one table message: e.g. n = 64 queries into 262,144 points
_BLOCK = 16


def index_bits(n_values: int) -> int:
    """l: OTs per query into ``n_values`` values."""
    return max(1, (n_values - 1).bit_length())


def _pads(hash_: CorrelationRobustHash, keys: np.ndarray, tweaks: np.ndarray) -> np.ndarray:
    """XOR over the first axis of F(keys[j, k], tweaks[j, k]): ``keys`` (l, K, 2) and
    ``tweaks`` (l, K); returns (K, 2) uint64."""
    hashed = hash_(keys.reshape(-1, 2), tweaks.reshape(-1)).reshape(keys.shape)
    acc = hashed[0].copy()
    for row in hashed[1:]:  # l is small: a few contiguous whole-array XORs
        acc ^= row
    return acc


def _check_values(values: np.ndarray, name: str, rows: int | None = None) -> np.ndarray:
    v = np.asarray(values)
    if v.dtype != np.uint8 or v.ndim != 2 or not 1 <= v.shape[1] <= _BLOCK or (
            rows is not None and len(v) != rows):
        want = f"{rows} rows" if rows is not None else "rows"
        raise ValueError(f"{name}: expected uint8 {want} of 1 to {_BLOCK} bytes, got "
                         f"{v.dtype} {v.shape}")
    return v


class SelectReceiver:
    """The device: ``request(indices)`` -> ``ot_ext_u``; ``receive(sel_table)`` -> (n, width)
    uint8 rows v[idx_i] ^ P_i. Runs on an ExtReceiver whose base OTs are done."""

    def __init__(self, ot: ExtReceiver, n_values: int, width: int) -> None:
        if n_values < 1 or not 1 <= width <= _BLOCK:
            raise ValueError(f"need at least one value of 1 to {_BLOCK} bytes")
        self._ot, self._n_values, self._width = ot, n_values, width
        self._l = index_bits(n_values)
        self._pending: tuple[np.ndarray, int, np.ndarray] | None = None

    def request(self, indices: np.ndarray) -> dict:
        """``ot_ext_u`` for one query per index (the index bits are the OT choices)."""
        idx = np.asarray(indices)
        if idx.ndim != 1 or not len(idx) or idx.dtype.kind not in "iu" or (
                (idx < 0) | (idx >= self._n_values)).any():
            raise ValueError(f"indices must be a non-empty vector in [0, {self._n_values})")
        if len(idx) * self._n_values * self._width > MAX_TABLE_BYTES:
            raise ValueError(f"{len(idx)} queries into {self._n_values} values exceed "
                             f"{MAX_TABLE_BYTES} table bytes")
        bits = (idx[:, None] >> np.arange(self._l)) & 1
        msg = self._ot.request(bits.reshape(-1))
        start, keys = self._ot.receive_random()
        self._pending = (idx.astype(np.int64), start, keys.reshape(len(idx), self._l, 2))
        return msg

    def receive(self, msg: object) -> np.ndarray:
        """v[idx_i] ^ P_i from the map owner's ``sel_table``."""
        if self._pending is None:
            raise ProtocolError(UNEXPECTED, "'sel_table' with no selection requested")
        idx, start, keys = self._pending
        n = len(idx)
        body = wire.fields(msg, "sel_table", ("start", "key", "table"))
        wire.integer(body, "start", start, start)
        hash_ = CorrelationRobustHash(wire.blob(body, "key", _BLOCK))
        table = np.frombuffer(wire.blob(body, "table", n * self._n_values * self._width),
                              np.uint8).reshape(n, self._n_values, self._width)
        js = np.arange(self._l)
        tweaks = (np.arange(n)[None, :] * self._l + js[:, None]) * self._n_values + idx
        pads = _pads(hash_, keys[:, js].transpose(1, 0, 2), tweaks)  # (n, 2)
        self._pending = None
        return table[np.arange(n), idx] ^ pads.view(np.uint8)[:, :self._width]


class SelectSender:
    """The map owner, holding ``values`` (N, width) uint8: ``respond(u, pads)`` ->
    ``sel_table`` with fresh ``pads`` (n, width) uint8, one per query. Runs on an ExtSender
    whose base OTs are done."""

    def __init__(self, ot: ExtSender, values: np.ndarray, max_queries: int = 4096) -> None:
        self._ot = ot
        self._values = _check_values(values, "values")
        self._l = index_bits(len(self._values))
        self._max_queries = max_queries

    def respond(self, msg: object, pads: np.ndarray) -> dict:
        """The table for the device's ``ot_ext_u``: every value under every query's pad."""
        n_values, width = self._values.shape
        body = wire.fields(msg, "ot_ext_u", ("start", "m", "u"))
        m = wire.integer(body, "m", 1, self._max_queries * self._l)
        n, rest = divmod(m, self._l)
        if rest or n * n_values * width > MAX_TABLE_BYTES:
            raise ProtocolError(BAD_REQUEST, f"field 'm': {m} OTs are not 1 to "
                                             f"{self._max_queries} queries of {self._l} "
                                             f"into {n_values} values")
        pads = _check_values(pads, "pads", n)
        if pads.shape[1] != width:
            raise ValueError(f"pads: {pads.shape[1]} bytes per row, values have {width}")
        start, k0, k1 = self._ot.respond_random(msg)
        k0, k1 = k0.reshape(n, self._l, 2), k1.reshape(n, self._l, 2)
        js, ks = np.arange(self._l), np.arange(n_values)
        pick = (2 * js[:, None] + ((ks[None, :] >> js[:, None]) & 1)).reshape(-1)  # (l, N)
        tweaks = js[:, None] * n_values + ks  # + i l N for query i
        key = secrets.token_bytes(_BLOCK)
        hash_ = CorrelationRobustHash(key)
        table = np.empty((n, n_values, width), np.uint8)
        for i in range(n):  # one query at a time: N l blocks of work each
            pairs = np.stack([k0[i], k1[i]], axis=1).reshape(-1, 2)  # row 2j + b: K_ij^b
            chosen = np.take(pairs, pick, axis=0).reshape(self._l, n_values, 2)
            masks = _pads(hash_, chosen, tweaks + i * self._l * n_values).view(np.uint8)
            table[i] = self._values ^ pads[i] ^ masks[:, :width]
        return {"t": "sel_table", "start": start, "key": key, "table": table.tobytes()}
