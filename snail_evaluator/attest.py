"""The evaluator's check of the garbler's signed digest, and its failpoints.

The garbler follows a session's last table frame with ``tables_end`` {sid, digest,
signature} (what it signs: snail_common/gc/attest.py). The evaluator hashes the stream as
it evaluates it (in the worker pool, frame by frame), and before it answers checks that
the digest signed is the digest of the bytes it received, and that the signature
verifies under the garbler key the client named in its ``session_start`` (``signer``): a
mismatch fails the session with ``digest``, naming the garbler or the server link, and
nothing is returned (a client that names no key, one that checks nothing itself, gets
the digest compared but no signature checked). The signed digest then goes to the
client in the ``stats``, which the client checks itself (its audit): so the client holds
the garbler's commitment to exactly the bytes that were evaluated, and this evaluator
cannot stand another one in.

Mixed into ``EvaluatorDaemon``; its call sites in tables.py are one line each.
Failpoints (snail_common/failpoints.py): ``evaluator.output_label`` flips a bit of the
first output label returned, ``evaluator.digest`` a bit of the digest forwarded.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

import numpy as np

from snail_common import failpoints
from snail_common.gc.attest import Statement
from snail_common.gc.stream import HEADER, Header, StreamError, scheme_id
from snail_common.net.conn import Connection
from snail_common.net.errors import DIGEST, STREAM, UNEXPECTED, ProtocolError

from .lanes import EvalLane, Solo
from .session import Session, StreamCut


class Digested:
    """An evaluation (Solo or a lane) whose fed bytes are added to its session's digest."""

    def __init__(self, s: Session, ev: Solo | EvalLane) -> None:
        self._s, self._ev = s, ev

    def feed(self, data: bytes | memoryview) -> None:
        """Runs in the worker pool, frames in stream order."""
        s = self._s
        t0 = time.thread_time()
        if len(s.head) < HEADER.size:
            s.head += bytes(memoryview(data)[: HEADER.size - len(s.head)])
        s.digest.update(data)
        s.check_s["digest_s"] += time.thread_time() - t0
        self._ev.feed(data)

    def __getattr__(self, name: str) -> Any:  # stream_complete, wait_done, lanes ...
        return getattr(self._ev, name)


class Attested:
    """The evaluator daemon's half of the signed digests."""

    @staticmethod
    def _digested(s: Session, ev: Solo | EvalLane) -> Digested:
        return Digested(s, ev)

    @staticmethod
    def _tables_end(s: Session, msg: dict[str, Any], evaluating: bool) -> bool:
        """Whether ``msg`` is this session's ``tables_end`` (kept for ``_attested``); it
        may come while the stream is buffered for labels, never before its last frame."""
        if msg["t"] != "tables_end" or msg["sid"] != s.sid:
            return False
        if evaluating:
            raise ProtocolError(STREAM, "the garbler signed off before its last table frame")
        if s.tables_end is not None:
            raise ProtocolError(UNEXPECTED, "the garbler signed its stream twice")
        s.tables_end = msg
        return True

    @staticmethod
    def _read_ahead(s: Session, recv: asyncio.Future) -> None:
        """The read still pending when a buffered stream turned out complete: cancelled,
        unless it already took the message after the last frame (the signed digest, for
        ``_attested``)."""
        if not recv.done():
            recv.cancel()
        elif not recv.cancelled() and recv.exception() is None:
            s.read_ahead = recv.result()

    async def _attested(self, conn: Connection, s: Session) -> None:
        """Wait for the garbler's signed digest (unless it came) and check it against
        the stream received; ProtocolError (``digest``) unless it holds."""
        if s.tables_end is None:
            msg, size = s.read_ahead or await conn.recv(self.options.session_timeout)
            s.read_ahead = None
            s.bytes_in += size
            if msg["t"] == "error" and msg.get("sid") == s.sid:  # it ended the stream
                self._fail(s, ProtocolError(msg["code"], f"the garbler reported: "
                                                         f"{msg['message']}"))
                raise StreamCut(garbler_ended=True)
            if not self._tables_end(s, msg, False):
                raise ProtocolError(UNEXPECTED, f"expected the signed digest of this "
                                                f"session, the garbler sent {msg['t']}")
        t0 = time.thread_time()
        msg = s.tables_end
        try:
            block = Header.unpack(s.head).block_gates
        except StreamError as exc:
            raise ProtocolError(STREAM, str(exc)) from None
        if msg["digest"] != s.digest.digest():
            raise ProtocolError(DIGEST, "the tables received are not the ones the garbler "
                                        "signed (the digests differ): the garbler or the "
                                        "server link altered them")
        statement = Statement(s.sid, s.circuit, s.hash, scheme_id(s.scheme), block,
                              msg["digest"])
        if s.signer is not None and not statement.verify(s.signer, msg["signature"]):
            raise ProtocolError(DIGEST, "the garbler's signature on its tables does not "
                                        "verify under the key the client named: the "
                                        "garbler or the server link")
        s.block_gates = block
        s.check_s["verify_s"] = time.thread_time() - t0

    @staticmethod
    def _outputs(ev: Solo | EvalLane | Digested) -> np.ndarray:
        """The active output labels to return (one spoiled: ``evaluator.output_label``)."""
        labels = ev.output_labels()
        if failpoints.fire("evaluator.output_label"):
            labels[0, 0] ^= np.uint64(1 << 40)
        return labels

    @staticmethod
    def _forwarded(s: Session) -> dict[str, Any]:
        """The signed digest for the client's ``stats`` (spoiled: ``evaluator.digest``)."""
        digest = s.tables_end["digest"]
        if failpoints.fire("evaluator.digest"):
            digest = bytes([digest[0] ^ 1]) + digest[1:]
        return {"tables_digest": digest, "block_gates": s.block_gates,
                "tables_signature": s.tables_end["signature"]}
