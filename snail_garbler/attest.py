"""The garbler's commitments: each run's table stream hashed as it is sent and signed with
a key of its own (what is signed: snail_common/gc/attest.py), so that a client that
garbles the run again (its audit) can prove to anyone that the tables were not the
function's.

The key is Ed25519: loaded from ``garbler.sign.key`` in the TLS directory (PEM, PKCS#8)
when that file exists, else made at start. Its public half goes in ``capabilities``,
``health`` and every session line, vouched for by the garbler's certificate key (an ECDSA
signature over it: the ``key_endorsement`` of ``capabilities``), so that a signature
names the certificate a third party can check.

``Attesting`` is mixed into ``GarblerDaemon``; its call sites in daemon.py are one line
each: ``frames`` in ``_stream`` (the stream as sent, failpoints applied, hashed in the
garbling thread), ``end`` after its last frame (``tables_end`` for the evaluator) and
``reply`` in ``_reply`` (the zero-labels and the signed fields of the client's stats).
"""

from __future__ import annotations

import logging
import time
import weakref
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from snail_common.gc.attest import (
    Statement,
    TableDigest,
    endorsement_message,
    public_bytes,
)
from snail_common.gc.stream import DEFAULT_SCHEME, HEADER, Header, scheme_id
from snail_common.net import messages, tls
from snail_common.net.service import Options
from snail_common.net.slots import Slot

from . import cheats

KEY_FILE = "garbler.sign.key"


def signing_key(tls_dir: str | Path | None) -> Ed25519PrivateKey:
    """The key in ``tls_dir/garbler.sign.key`` if there is one, else a new one."""
    path = Path(tls_dir) / KEY_FILE if tls_dir else None
    if path is None or not path.exists():
        return Ed25519PrivateKey.generate()
    try:
        key = serialization.load_pem_private_key(path.read_bytes(), None)
    except (OSError, ValueError) as exc:
        raise tls.TLSFileError(f"{path} cannot be read as a signing key: {exc}") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise tls.TLSFileError(f"{path} is not an Ed25519 private key")
    return key


class _Commit:
    """One session's stream as it goes out: its digest, then its signed statement."""

    def __init__(self, req: dict[str, Any], key: Ed25519PrivateKey) -> None:
        self.req, self._key = req, key
        self.digest = TableDigest()
        # the output zero-labels of the garbling actually streamed, once it is all sent:
        # the labels, not that garbling (a commitment is kept per garbler in a weak
        # dictionary, and a value that held its key would keep both alive for good)
        self.zero: np.ndarray | None = None
        self.statement: Statement | None = None
        self.signature = b""
        self.cpu_s = {"digest_s": 0.0, "sign_s": 0.0}

    def stream(self, garbler: Any) -> Iterator[bytes | memoryview]:
        """Runs in the garbling threads, frame by frame."""
        frames, streamed = cheats.frames(garbler, self.req)
        block = None
        for frame in frames:
            t0 = time.thread_time()
            if block is None:
                block = Header.unpack(bytes(frame[: HEADER.size])).block_gates
            self.digest.update(frame)
            self.cpu_s["digest_s"] += time.thread_time() - t0
            yield frame
        self.zero = streamed.output_zero_labels
        t0 = time.thread_time()
        req = self.req
        self.statement = Statement(req["sid"], req["circuit"], req["hash"],
                                   scheme_id(req.get("scheme", DEFAULT_SCHEME)), block or 0,
                                   self.digest.digest())
        self.signature = self.statement.sign(self._key)
        self.cpu_s["sign_s"] += time.thread_time() - t0


class Attestor:
    """The signing key and the commitments of the sessions under way."""

    def __init__(self, tls_dir: str | Path | None) -> None:
        self.key = signing_key(tls_dir)
        self.public = public_bytes(self.key)
        self.endorsement = (tls.endorse(tls_dir, "garbler", endorsement_message(self.public))
                            if tls_dir else b"")
        self._commits: weakref.WeakKeyDictionary[Any, _Commit] = weakref.WeakKeyDictionary()
        self._digests: dict[tuple[str, bytes], bytes] = {}  # for the session lines

    def frames(self, garbler: Any, req: dict[str, Any]) -> Iterator[bytes | memoryview]:
        """The session's table frames as sent, each added to its digest."""
        commit = self._commits[garbler] = _Commit(req, self.key)
        return commit.stream(garbler)

    def end(self, garbler: Any) -> dict[str, Any]:
        """The ``tables_end`` message that follows the last frame: the signed digest."""
        commit = self._commits[garbler]
        return messages.make("tables_end", sid=commit.req["sid"],
                             digest=commit.statement.tables, signature=commit.signature)

    def reply(self, garbler: Any, timing: dict[str, float], peer: str
              ) -> tuple[np.ndarray, dict[str, Any]]:
        """The output zero-labels to send the client and its stats' signed fields (the
        ``outputs`` statement over those labels); ``timing`` gains this session's
        digest and signing CPU seconds."""
        commit = self._commits[garbler]
        zero = cheats.zero_labels(commit.zero, commit.req)
        t0 = time.thread_time()
        signature = commit.statement.with_outputs(zero).sign(self.key)
        commit.cpu_s["sign_s"] += time.thread_time() - t0
        timing.update(commit.cpu_s)
        self._digests[peer, commit.req["sid"]] = commit.statement.tables
        return zero, {"tables_digest": commit.statement.tables,
                      "block_gates": commit.statement.block_gates,
                      "outputs_signature": signature}

    def logged(self, peer: str, sid: bytes) -> dict[str, str]:
        """What a session's line adds: the signing key and the digest signed, if any."""
        digest = self._digests.pop((peer, sid), None)
        return {"signer": self.public.hex(), **({"digest": digest.hex()} if digest else {})}


class Attesting:
    """The garbler daemon's signing key, announced, and its session lines."""

    attest: Attestor

    def __init__(self, options: Options, logger: logging.Logger) -> None:
        super().__init__(options, logger)
        self.attest = Attestor(options.tls_dir)

    def capabilities(self) -> dict[str, Any]:
        msg = super().capabilities()
        msg["signing_key"] = self.attest.public
        if self.attest.endorsement:
            msg["key_endorsement"] = self.attest.endorsement
        messages.validate(msg)
        return msg

    def health(self) -> dict[str, Any]:
        msg = super().health()
        msg["signing_key"] = self.attest.public.hex()
        messages.validate(msg)
        return msg

    def startup_fields(self) -> dict[str, Any]:
        return {**super().startup_fields(), "signing_key": self.attest.public.hex()}

    def finish(self, slot: Slot | None, record: dict[str, Any]) -> None:
        peer = slot.peer if slot is not None else ""
        super().finish(slot, {**record, **self.attest.logged(peer, record["sid"])})
