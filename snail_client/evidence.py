"""The evidence a client keeps when an audit catches the garbler (``snail-evidence/1``),
and its check by anyone holding the file (``snail-bench verify-evidence``).

A file holds one run: its circuit (id and content hash), scheme and block size, the run's
seed, offset and hash key (that run's only: every run has fresh ones, so the file gives
away nothing of any other run), what the garbler signed (the ``tables`` statement as the
evaluator forwarded it, the ``outputs`` statement the garbler sent with its zero-labels:
snail_common/gc/attest.py), its signing key, the endorsement of that key by its
certificate key and the certificate itself, what the client recomputed, and both
servers' certificate fingerprints.

``verify`` needs nothing else: it checks that the key is the certificate's (and, given
the CA, that the CA issued the certificate), that the signatures are the key's, garbles
the run again from the file's seed, offset and key, and finds the garbler cheated when
a statement it signed differs from that run's tables or zero-labels, or when it signed
two different streams for one run.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from cryptography import x509
from cryptography.hazmat.primitives import serialization

from snail_common import families
from snail_common.circuit import registry
from snail_common.gc import Garbler, labels_from_bytes, labels_to_bytes
from snail_common.gc.attest import Statement, TableDigest, endorsement_message, outputs_digest
from snail_common.gc.stream import SCHEME_NAMES, scheme_id
from snail_common.net.tls import endorsed, issued_by

FORMAT = "snail-evidence/1"


def regarble(circuit_id: str, seed: bytes, delta: np.ndarray | bytes, key: bytes,
             scheme: str | int, block_gates: int) -> tuple[bytes, np.ndarray]:
    """(digest of the table stream, output zero-labels) of one run, garbled here as the
    garbler should have (the engine does not matter: both make the same stream)."""
    _, schedule = registry.compiled(circuit_id)
    garbler = Garbler(schedule, seed, delta, key, block_gates=block_gates, scheme=scheme)
    digest = TableDigest()
    for frame in garbler.frames():
        digest.update(frame)
    return digest.digest(), garbler.output_zero_labels


@dataclass(frozen=True)
class Signed:
    """What the garbler signed for one run, as the client received it."""

    tables: Statement  # as the evaluator forwarded it
    tables_signature: bytes
    outputs: Statement  # as the garbler sent it with its zero-labels
    outputs_signature: bytes
    signing_key: bytes
    endorsement: bytes
    certificate: bytes  # the garbler's, DER, as the client's TLS session saw it


def write(directory: Path, run: int, seed: bytes, delta: np.ndarray, key: bytes,
          signed: Signed, recomputed: tuple[bytes, np.ndarray] | None,
          servers: dict[str, str], detail: str) -> Path:
    """Write the evidence of run ``run`` into ``directory``; its path. ``recomputed``: the
    run garbled again (None where the signatures alone prove the case)."""
    directory.mkdir(parents=True, exist_ok=True)
    t, o = signed.tables, signed.outputs
    record = {
        "format": FORMAT, "detail": detail, "run": run, "written": time.time(),
        "circuit": t.circuit, "content_hash": t.content_hash,
        "scheme": SCHEME_NAMES[t.scheme], "sid": t.sid.hex(),
        "seed": seed.hex(), "offset": labels_to_bytes(delta).hex(), "key": key.hex(),
        "signed": {
            "tables": {"block_gates": t.block_gates, "digest": t.tables.hex(),
                       "signature": signed.tables_signature.hex()},
            "outputs": {"block_gates": o.block_gates, "digest": o.tables.hex(),
                        "zero_labels_digest": (o.outputs or b"").hex(),
                        "signature": signed.outputs_signature.hex()},
        },
        "signing_key": signed.signing_key.hex(),
        "key_endorsement": signed.endorsement.hex(),
        "garbler_certificate": x509.load_der_x509_certificate(signed.certificate)
        .public_bytes(serialization.Encoding.PEM).decode() if signed.certificate else "",
        "recomputed": None if recomputed is None else {
            "digest": recomputed[0].hex(),
            "zero_labels_digest": outputs_digest(recomputed[1]).hex()},
        "servers": {role: {"certificate_sha256": fp} for role, fp in servers.items()},
    }
    path = directory / f"evidence-{t.sid.hex()[:16]}-run{run}.json"
    path.write_text(json.dumps(record, indent=1) + "\n")
    return path


class Unproven(Exception):
    """The file does not prove that the garbler cheated; the message says why."""


def verify(path: Path, ca_pem: bytes | None = None) -> dict[str, Any]:
    """What the evidence at ``path`` proves (``{"proven": True, "garbler": fingerprint,
    "because": ...}``); Unproven naming why it proves nothing."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise Unproven(f"{path}: not a readable JSON file ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise Unproven(f"{path}: not a {FORMAT} file")
    try:
        return _verify(doc, ca_pem)
    except (KeyError, TypeError, ValueError) as exc:
        raise Unproven(f"{path}: malformed {FORMAT} file ({exc!r})") from None


def _verify(doc: dict[str, Any], ca_pem: bytes | None) -> dict[str, Any]:
    key = bytes.fromhex(doc["signing_key"])
    cert_pem = doc["garbler_certificate"].encode()
    if not cert_pem:
        raise Unproven("the file holds no garbler certificate: its signing key is not "
                       "shown to be the garbler's")
    cert = x509.load_pem_x509_certificate(cert_pem).public_bytes(serialization.Encoding.DER)
    fingerprint = hashlib.sha256(cert).hexdigest()
    if fingerprint != doc["servers"]["garbler"]["certificate_sha256"]:
        raise Unproven("the certificate is not the garbler's the client talked to (its "
                       "fingerprint differs)")
    if ca_pem is not None and not issued_by(cert, ca_pem):
        raise Unproven("the CA given did not issue the garbler's certificate")
    if not endorsed(cert, endorsement_message(key), bytes.fromhex(doc["key_endorsement"])):
        raise Unproven("the garbler's certificate key did not endorse the signing key")
    sid, scheme = bytes.fromhex(doc["sid"]), scheme_id(doc["scheme"])
    signed = []  # the statements the garbler's key really signed
    for kind in ("tables", "outputs"):
        part = doc["signed"][kind]
        outputs = bytes.fromhex(part["zero_labels_digest"]) if kind == "outputs" else None
        statement = Statement(sid, doc["circuit"], doc["content_hash"], scheme,
                              int(part["block_gates"]), bytes.fromhex(part["digest"]),
                              outputs)
        if statement.verify(key, bytes.fromhex(part["signature"])):
            signed.append(statement)
    if not signed:
        raise Unproven("no statement in the file carries the garbler's signature")
    if len({(s.block_gates, s.tables) for s in signed}) > 1:
        return _proven(fingerprint, "the garbler signed two different table streams for "
                                    "one run")
    families.register_all()
    iface = registry.interface(doc["circuit"])
    if iface.content_hash != doc["content_hash"]:
        raise Unproven(f"this build's {doc['circuit']} is another circuit (content hash "
                       f"{iface.content_hash[:16]}..., the file's {doc['content_hash'][:16]}"
                       f"...): it cannot garble the run again")
    delta = labels_from_bytes(bytes.fromhex(doc["offset"]))[0]
    digest, zero = regarble(doc["circuit"], bytes.fromhex(doc["seed"]), delta,
                            bytes.fromhex(doc["key"]), scheme, signed[0].block_gates)
    for statement in signed:
        if statement.tables != digest:
            return _proven(fingerprint, f"the garbler signed tables ({statement.kind} "
                                        f"statement) that are not this circuit's for the "
                                        f"run's seed, offset and key")
        if statement.outputs is not None and statement.outputs != outputs_digest(zero):
            return _proven(fingerprint, "the garbler signed output zero-labels that are not "
                                        "this run's")
    raise Unproven("the garbler's signed tables and zero-labels are this run's: the "
                   "file proves no cheating by the garbler")


def _proven(fingerprint: str, because: str) -> dict[str, Any]:
    return {"proven": True, "party": "garbler", "garbler_certificate_sha256": fingerprint,
            "because": because}
