"""IKNP OT extension (Ishai-Kilian-Nissim-Petrank 2003): 128 base OTs, then any number of
1-out-of-2 OTs of 128-bit messages at the cost of AES and a bit-matrix transpose.

The extension receiver R (choice bits r, m of them) is the base-OT *sender*; the extension
sender S (messages) is the base-OT *receiver*, with 128 random choice bits s.
  R: t^i = G(k_i^0), u^i = t^i ^ G(k_i^1) ^ r                        (rows, m bits each)
  S: q^i = G(k_i^{s_i}) ^ s_i u^i = t^i ^ s_i r;  as columns q_j = t_j ^ r_j s
  random:     S's keys are H(j, q_j) and H(j, q_j ^ s); R's is H(j, t_j); nothing is sent
  chosen:     S sends y_j^b = x_j^b ^ H(j, q_j ^ b s);  R takes x_j^{r_j} = y_j^{r_j} ^ H(j, t_j)
  correlated: S's x_j^0 = H(j, q_j), x_j^1 = x_j^0 ^ Delta; it sends
              w_j = H(j, q_j) ^ H(j, q_j ^ s) ^ Delta;  R takes H(j, t_j) ^ r_j w_j
G is AES-128-CTR, H the correlation-robust hash of ``blocks.py`` keyed by a hash of the
base-OT transcript; j counts OTs over the whole session, so batches never reuse a tweak or
PRG output. Correlated OT is what garbled-circuit input labels need: (L0, L0 ^ D) with the
garbler's global offset as Delta, at 16 bytes per OT instead of 32.

Security: semi-honest, as the rest of the project. IKNP is NOT secure against a malicious
receiver: one that puts different choice vectors into different rows of u learns bits of s
from which OTs succeed, and with s both messages of every OT (KOS 2015 adds the consistency
check that stops this). A malicious sender can make the receiver's output depend on its
choice bits (selective failure). Both need the actively secure variant, not this module.

Messages (dicts of bytes and ints, msgpack-able; the daemons carry them in their frames):
  R -> S  ``ot_base_a`` {a}                      (base OT, once per session)
  S -> R  ``ot_base_b`` {b}
  R -> S  ``ot_ext_u``  {start, m, u}            (per batch)
  S -> R  ``ot_ext_y``  {start, y} or ``ot_ext_c`` {start, w} (nothing for random OT)
"""

from __future__ import annotations

import hashlib
import secrets

import numpy as np

from ..net.errors import BAD_REQUEST, UNEXPECTED, ProtocolError
from . import wire
from .base import BaseReceiver, BaseSender
from .blocks import KAPPA, CorrelationRobustHash, RowStreams, block_of_bits, pack_bits, transpose
from .group import Random

BLOCK = 16  # bytes per OT message
MAX_BATCH = 1 << 21  # OTs per batch a party accepts by default (u: 32 MiB, y: 64 MiB)
_MAX_INDEX = (1 << 63) - 1  # OT indices are the hash tweak, one 64-bit word
_PERSON = b"snail-ot-crh"


def _crh(a: bytes, b: bytes) -> CorrelationRobustHash:
    """The hash of one session, keyed by the base-OT transcript both sides hold."""
    return CorrelationRobustHash(hashlib.blake2b(a + b, digest_size=BLOCK,
                                                 person=_PERSON).digest())


def as_blocks(value: object, m: int, name: str) -> np.ndarray:
    """``m`` 128-bit messages (bytes of 16*m, or any array of that many bytes, such as
    (m, 2) uint64 labels) as an (m, 2) uint64 array."""
    arr = np.frombuffer(value, dtype=np.uint8) if isinstance(value, (bytes, bytearray)) \
        else np.ascontiguousarray(value).reshape(-1).view(np.uint8)
    if arr.size != m * BLOCK:
        raise ValueError(f"{name}: expected {m} blocks of {BLOCK} bytes, got {arr.size} bytes")
    return arr.view(np.uint64).reshape(m, 2)


def _check_batch_size(m: int, max_batch: int) -> None:
    if not 1 <= m <= max_batch:
        raise ValueError(f"an OT batch holds 1 to {max_batch} OTs, got {m}")


class ExtReceiver:
    """The party with the choice bits. ``start()``, ``base_done(b)``, then per batch
    ``request(choices)`` and ``receive(answer)`` -> the chosen messages, (m, 2) uint64."""

    def __init__(self, rng: Random = secrets.token_bytes, max_batch: int = MAX_BATCH) -> None:
        self._base = BaseSender(KAPPA, rng)
        self._max = max_batch
        self._streams: tuple[RowStreams, RowStreams] | None = None
        self._crh: CorrelationRobustHash | None = None
        self._next = 0
        self._pending: tuple[int, np.ndarray, np.ndarray] | None = None  # start, r, t_j

    def start(self) -> dict:
        return self._base.first()

    def base_done(self, msg: object) -> None:
        """Finish the base OTs with the sender's ``ot_base_b``."""
        keys0, keys1 = self._base.finish(msg)
        self._streams = (RowStreams(keys0), RowStreams(keys1))
        self._crh = _crh(self._base.a_point, msg["b"])

    def request(self, choices: np.ndarray) -> dict:
        """The ``ot_ext_u`` message for the next batch, one OT per choice bit."""
        if self._streams is None or self._pending is not None:
            raise RuntimeError("request() needs finished base OTs and no batch in flight")
        r = np.asarray(choices)
        if r.ndim != 1 or not np.isin(r, (0, 1)).all():
            raise ValueError("choices must be a vector of 0/1")
        m = len(r)
        _check_batch_size(m, self._max)
        nbytes = (m + 7) // 8
        t = self._streams[0].take(nbytes)
        u = t ^ self._streams[1].take(nbytes) ^ pack_bits(r)[None, :]
        start, self._next = self._next, self._next + m
        self._pending = (start, r.astype(bool), transpose(t)[:m])
        return {"t": "ot_ext_u", "start": start, "m": m, "u": u.tobytes()}

    def receive(self, msg: object) -> np.ndarray:
        """The chosen messages from the sender's ``ot_ext_y`` or ``ot_ext_c``."""
        if self._pending is None:
            raise ProtocolError(UNEXPECTED, "an OT answer with no batch requested")
        start, r, t = self._pending
        m = len(r)
        kind = msg.get("t") if isinstance(msg, dict) else None
        body = wire.fields(msg, "ot_ext_c" if kind == "ot_ext_c" else "ot_ext_y",
                           ("start", "w" if kind == "ot_ext_c" else "y"))
        wire.integer(body, "start", start, start)
        pad = self._crh(t, start)
        if kind == "ot_ext_c":
            w = as_blocks(wire.blob(body, "w", m * BLOCK), m, "w")
            out = np.where(r[:, None], pad ^ w, pad)
        else:
            y = np.frombuffer(wire.blob(body, "y", 2 * m * BLOCK), np.uint64).reshape(m, 2, 2)
            out = y[np.arange(m), r.astype(np.intp)] ^ pad
        self._pending = None
        return out

    def receive_random(self) -> tuple[int, np.ndarray]:
        """Random OT: (start, H(j, t_j)) for the batch in flight, the key the sender's
        ``respond_random`` gives for each choice; no answer message is needed."""
        if self._pending is None:
            raise RuntimeError("receive_random() needs a batch in flight")
        start, _, t = self._pending
        self._pending = None
        return start, self._crh(t, start)


class ExtSender:
    """The party with the messages. ``base_reply(a)`` -> ``ot_base_b``, then per batch
    ``respond_chosen(u, x0, x1)`` or ``respond_correlated(u, delta)``."""

    def __init__(self, rng: Random = secrets.token_bytes, max_batch: int = MAX_BATCH) -> None:
        self._s_bits = np.unpackbits(np.frombuffer(rng(KAPPA // 8), np.uint8),
                                     bitorder="little")
        self._s = block_of_bits(self._s_bits)
        self._base = BaseReceiver(self._s_bits, rng)
        self._max = max_batch
        self._streams: RowStreams | None = None
        self._crh: CorrelationRobustHash | None = None
        self._next = 0

    def base_reply(self, msg: object) -> dict:
        """Answer the receiver's ``ot_base_a`` (the base OTs, with choice bits s)."""
        reply = self._base.reply(msg)
        self._streams = RowStreams(self._base.keys)
        self._crh = _crh(msg["a"], reply["b"])
        return reply

    def _request(self, msg: object) -> tuple[int, int, np.ndarray]:
        """(start, m, u rows) of the receiver's ``ot_ext_u``, checked; no state changes."""
        if self._streams is None:
            raise ProtocolError(UNEXPECTED, "'ot_ext_u' before the base OTs")
        body = wire.fields(msg, "ot_ext_u", ("start", "m", "u"))
        start = wire.integer(body, "start", 0, _MAX_INDEX)
        if start != self._next:
            raise ProtocolError(BAD_REQUEST, f"field 'start': expected {self._next}, "
                                             f"got {start}")
        m = wire.integer(body, "m", 1, min(self._max, _MAX_INDEX - start))
        nbytes = (m + 7) // 8
        u = np.frombuffer(wire.blob(body, "u", KAPPA * nbytes), np.uint8).reshape(KAPPA, nbytes)
        return start, m, u

    def _q(self, start: int, m: int, u: np.ndarray) -> np.ndarray:
        """The columns q_j of a checked request (this advances the PRG streams)."""
        rows = self._streams.take(u.shape[1])
        rows ^= u * self._s_bits[:, None]  # s_i u^i: the 0/1 factor keeps whole bytes
        self._next = start + m
        return transpose(rows)[:m]

    def respond_chosen(self, msg: object, x0: object, x1: object) -> dict:
        """``ot_ext_y``: the pairs (x0[j], x1[j]), each under the hash only its chosen side
        can compute."""
        start, m, u = self._request(msg)
        x0, x1 = as_blocks(x0, m, "x0"), as_blocks(x1, m, "x1")
        q = self._q(start, m, u)
        y = np.stack([x0 ^ self._crh(q, start), x1 ^ self._crh(q ^ self._s, start)], axis=1)
        return {"t": "ot_ext_y", "start": start, "y": y.tobytes()}

    def respond_random(self, msg: object) -> tuple[int, np.ndarray, np.ndarray]:
        """Random OT: (start, k0, k1), both (m, 2) uint64; the receiver holds k_{r_j}[j]
        and nothing about the other key. Sends nothing."""
        start, m, u = self._request(msg)
        q = self._q(start, m, u)
        return start, self._crh(q, start), self._crh(q ^ self._s, start)

    def respond_correlated(self, msg: object, delta: object) -> tuple[dict, np.ndarray]:
        """(``ot_ext_c``, x0): the receiver gets x0[j] ^ r_j Delta; x0 comes out of the OT
        (random, fixed by the hash), the sender keeps it as its zero-messages."""
        d = as_blocks(delta, 1, "delta")
        start, m, u = self._request(msg)
        q = self._q(start, m, u)
        x0 = self._crh(q, start)
        w = x0 ^ self._crh(q ^ self._s, start) ^ d
        return {"t": "ot_ext_c", "start": start, "w": w.tobytes()}, x0
