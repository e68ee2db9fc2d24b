"""The client's audits: it trusts neither server alone, and names the one that cheats.

The servers were trusted to follow the protocol; the output-label check caught a
tampering evaluator, nothing caught a garbler (it sends the zero-labels the client
decodes with: L0 ^ D for L0 flips a bit silently). But the seed, the offset and the hash
key are the client's, so it can garble any run again itself. Every run:

1. the signed digests are checked (the garbler's statements: snail_common/gc/attest.py),
   always, under the key the garbler announced in its ``capabilities``: the ``tables``
   statement the evaluator forwards (it does not verify: the evaluator forwarded
   something the garbler did not sign), the ``outputs`` statement over the zero-labels
   received (it does not verify: the garbler sent it so), and both must name one stream
   (else the garbler signed two);
2. the labels are decoded; a label that is neither L0 nor L0 ^ D fails the run;
3. with probability ``rate`` (drawn from the OS CSPRNG for every run before its result
   is looked at, so it is independent of padding and of the data), and on every failing
   run, the run is garbled again here (``evidence.regarble``: the native engine where it
   runs, numpy else; the block size is the signed one, since the stream's header and so
   its digest depend on it) and compared. Tables or zero-labels that differ from what
   the garbler signed name the garbler, provably: the evidence file
   (``--evidence DIR``) convinces anyone (``snail-bench verify-evidence``); right tables
   and zero-labels with an invalid label name the evaluator, or, for a circuit with map
   owner inputs (whose labels come by OT from the garbler and the map owner),
   ``evaluator-or-ot``.

Nothing the client sends depends on the draw: the audit runs after the run, on the client
alone, and the run's timings that size garble-ahead and pick the scheme exclude it. A
party caught is refused for the rest of the runner's life (``admit``); in a fleet the run
is tried again on another replica.

A run the evaluator failed because the garbler's tables reached it changed (``link``: a
frame of the table link fails its seal; ``digest``: the tables are not the ones the
garbler signed) is an integrity failure too, blaming ``server-link`` (``named``, around
every run of the blocking runners, blocking.py and threaded.py): the evaluator cannot
tell a garbler that sends wrong bytes from a link that changes them, and the client,
which got no signed stream of the run, cannot either. No wrong answer came of it, so
neither server is refused: the next session opens a new link.
"""

from __future__ import annotations

import asyncio
import math
import secrets
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from snail_common.gc import IntegrityError, decode_output_labels
from snail_common.gc.attest import Statement, outputs_digest
from snail_common.gc.stream import scheme_id
from snail_common.net.errors import TABLES_CHANGED

from . import evidence
from .links import Link, ServiceError
from .replicas import ReplicaSet
from .sessions import Prepared

# The default share of runs audited (snail-bench audits, native engine, docs/performance.md):
# an audit costs the client 3 ms of CPU at n = 6 (an unaudited run 1.4 ms; the two servers
# spend about 17 ms on the run) and 0.1 s at n = 256 (a run takes 0.4-0.5 s). At 1/8 the
# client's CPU per run grows by 0.37 ms (n = 6) and 12 ms (n = 256, under 3 % of a run's
# time), and a garbler cheating on every run of a padded localization (20 runs) is caught
# with probability 1 - (7/8)^20 = 0.93 in that localization.
DEFAULT_AUDIT_RATE = 1 / 8
_DRAW = 1 << 53
INTEGRITY = "integrity"
SERVER_LINK = "server-link"
T = TypeVar("T")


class IntegrityFailure(ServiceError):
    """A run failed the integrity checks: ``party`` (garbler, evaluator, evaluator-or-ot
    or server-link) is to blame, ``run`` its index among the runner's runs, ``evidence``
    the file written (if any)."""

    def __init__(self, party: str, run: int, detail: str, evidence: Path | None = None,
                 link: Link | None = None, retry: bool = False) -> None:
        where = f"; evidence in {evidence}" if evidence else ""
        super().__init__(f"integrity check failed on run {run}, the {party} is to blame: "
                         f"{detail}{where}", INTEGRITY, link, retry)
        self.party, self.run, self.detail, self.evidence = party, run, detail, evidence
        self.audits: dict[str, int] = {}  # the frame's audit counts (localize.py sets them)

    def record(self) -> dict[str, Any]:
        """The ``error`` field of the failed result (docs/formats.md)."""
        out: dict[str, Any] = {"kind": INTEGRITY, "party": self.party, "run": self.run,
                               "detail": self.detail}
        if self.evidence is not None:
            out["evidence"] = str(self.evidence)
        return out


@dataclass
class _Screened:
    """A run after its signatures and decoding: what an audit then compares."""

    run: int
    session: Prepared
    zero: np.ndarray
    signed: evidence.Signed
    audit: bool
    outputs: np.ndarray | None = None
    invalid: str = ""  # why decoding failed, if it did


@dataclass
class Audits:
    """The runner's audits: the rate, the counts, the evidence folder, who is refused."""

    rate: float = DEFAULT_AUDIT_RATE
    evidence_dir: Path | None = None
    runs: int = 0
    audited: int = 0
    failed: int = 0
    refused: dict[str, str] = field(default_factory=dict)  # _server(link) -> party
    audit_s: float = 0.0  # wall seconds of the last run's audit (0: not audited)

    def __post_init__(self) -> None:
        if not (0.0 <= self.rate <= 1.0) or math.isnan(self.rate):
            raise ValueError(f"--audit-rate must be in [0, 1], got {self.rate}")
        self._threshold = round(self.rate * _DRAW)

    def counts(self) -> dict[str, int]:
        return {"runs": self.runs, "audited": self.audited, "failed": self.failed}

    def admit(self, session: Prepared, cancel: Callable[[Prepared], None],
              replicas: Mapping[str, ReplicaSet]) -> None:
        """Refuse (``cancel``) a session at a server caught cheating earlier:
        ServiceError, which may run again where the role has other ``replicas``."""
        for role, link in (("garbler", session.garbler), ("evaluator", session.evaluator)):
            party = self.refused.get(_server(link))
            if party is not None:
                cancel(session)
                replicas[role].shun_link(link, math.inf)
                raise ServiceError(f"{link.where} failed an integrity check "
                                   f"earlier ({party} blamed): refused for the rest of this "
                                   f"session", INTEGRITY, link, retry=replicas[role].several())

    async def check(self, session: Prepared, zero: np.ndarray, active: np.ndarray,
                    g_stats: dict[str, Any], e_stats: dict[str, Any],
                    replicas: Mapping[str, ReplicaSet]) -> np.ndarray:
        """The decoded outputs of a run, once its checks hold; IntegrityFailure else
        (to be tried again where the role at fault has other ``replicas``)."""
        screened = self._screen(session, zero, active, g_stats, e_stats, replicas)
        if not screened.audit:
            return screened.outputs
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        recomputed = await loop.run_in_executor(None, _regarble, screened)
        self.audit_s = loop.time() - t0
        return self._settle(screened, recomputed, replicas)

    async def named(self, invocation: Awaitable[T]) -> T:
        """The result of ``invocation`` (a secure run); where the evaluator failed it for
        tables that reached it changed, whichever server passed its word on, an
        IntegrityFailure blaming the server link, counted as a run checked and failed."""
        try:
            return await invocation
        except IntegrityFailure:
            raise
        except ServiceError as exc:
            if exc.code not in TABLES_CHANGED:
                raise
            run = self.runs
            self.runs += 1
            self.failed += 1
            raise IntegrityFailure(
                SERVER_LINK, run, f"the garbler's tables were changed on the server link, "
                f"or sent so by the garbler: the evaluator cannot tell a garbler that sends "
                f"wrong bytes from a link that changes them ({exc})",
                link=exc.link) from None

    def draw(self) -> bool:
        """Whether to audit the next run: True with probability ``rate`` (OS CSPRNG)."""
        return secrets.randbelow(_DRAW) < self._threshold

    def _screen(self, session: Prepared, zero: np.ndarray, active: np.ndarray,
                g_stats: dict[str, Any], e_stats: dict[str, Any],
                replicas: Mapping[str, ReplicaSet]) -> _Screened:
        run, audit = self.runs, self.draw()  # drawn before anything of the run is seen
        self.runs += 1
        self.audit_s = 0.0
        key = session.garbler.conn.info.get("signing_key")
        if key is None:
            raise ServiceError(f"{session.garbler.where} announces no signing key: its "
                               f"tables cannot be checked (an older garbler?)")
        fields = ("tables_digest", "block_gates", "tables_signature")
        if not all(f in e_stats for f in fields):
            self._fail("evaluator", run, session, "the evaluator forwarded no signed digest "
                                                  "of the tables", replicas)
        if not all(f in g_stats for f in (*fields[:2], "outputs_signature")):
            self._fail("garbler", run, session, "the garbler signed no digest of its "
                                                "tables", replicas)
        base = (session.sid, session.circuit_id, session.iface.content_hash,
                scheme_id(session.scheme))
        tables = Statement(*base, e_stats["block_gates"], e_stats["tables_digest"])
        outputs = Statement(*base, g_stats["block_gates"], g_stats["tables_digest"],
                            outputs_digest(zero))
        signed = evidence.Signed(tables, e_stats["tables_signature"], outputs,
                                 g_stats["outputs_signature"], key,
                                 session.garbler.conn.info.get("key_endorsement", b""),
                                 _certificate(session.garbler))
        if not tables.verify(key, signed.tables_signature):
            self._fail("evaluator", run, session, "the signed digest the evaluator forwarded "
                                                  "is not the garbler's", replicas)
        if not outputs.verify(key, signed.outputs_signature):
            self._fail("garbler", run, session, "the garbler's signature on its output "
                                                "zero-labels does not verify", replicas)
        screened = _Screened(run, session, zero, signed, audit)
        if (tables.block_gates, tables.tables) != (outputs.block_gates, outputs.tables):
            self._fail("garbler", run, session, "the garbler signed two different table "
                                                "streams for this run", replicas,
                       self._evidence(screened, None, "two streams signed for one run"))
        try:
            screened.outputs = decode_output_labels(session.delta, zero, active)
        except IntegrityError as exc:
            screened.invalid, screened.audit = str(exc), True  # every failing run
        if screened.audit:
            self.audited += 1
        return screened

    def _settle(self, s: _Screened, recomputed: tuple[bytes, np.ndarray],
                replicas: Mapping[str, ReplicaSet]) -> np.ndarray:
        """Compare the audit's run with what was signed and returned."""
        digest, zero = recomputed
        lie = ("the tables the garbler signed are not this circuit's for the run's seed, "
               "offset and key" if digest != s.signed.tables.tables else
               "the output zero-labels the garbler sent are not this run's"
               if not np.array_equal(zero, s.zero) else "")
        if lie:
            self._fail("garbler", s.run, s.session, lie, replicas,
                       self._evidence(s, recomputed, lie))
        if s.invalid:
            party = "evaluator-or-ot" if s.session.owner_bits else "evaluator"
            self._fail(party, s.run, s.session, f"the garbler's tables and zero-labels are "
                                                f"right, the output labels returned are not "
                                                f"({s.invalid})", replicas)
        return s.outputs

    def _evidence(self, s: _Screened, recomputed: tuple[bytes, np.ndarray] | None,
                  detail: str) -> Path | None:
        if self.evidence_dir is None:
            return None
        session = s.session
        return evidence.write(self.evidence_dir, s.run, session.seed, session.delta,
                              session.key, s.signed, recomputed,
                              {"garbler": _fingerprint(session.garbler),
                               "evaluator": _fingerprint(session.evaluator)}, detail)

    def _fail(self, party: str, run: int, session: Prepared, detail: str,
              replicas: Mapping[str, ReplicaSet], path: Path | None = None) -> None:
        """Count the failure, refuse the party (both servers when it cannot be told:
        ``evaluator-or-ot``), pass over its replica for good, and raise."""
        self.failed += 1
        roles = {"garbler": ("garbler",), "evaluator": ("evaluator",)}.get(
            party, ("garbler", "evaluator"))
        links = {"garbler": session.garbler, "evaluator": session.evaluator}
        for role in roles:
            self.refused[_server(links[role])] = party
            replicas[role].shun_link(links[role], math.inf)
        raise IntegrityFailure(party, run, detail, path, links[roles[0]],
                               retry=all(replicas[role].several() for role in roles))


def named_signer(garbler: Link) -> dict[str, bytes]:
    """How a session names the garbler's signing key to the evaluator (its
    ``session_start``), which then checks the garbler's signature under that key."""
    key = garbler.conn.info.get("signing_key")
    return {"signer": key} if key is not None else {}


def _regarble(s: _Screened) -> tuple[bytes, np.ndarray]:
    session, t = s.session, s.signed.tables
    return evidence.regarble(session.circuit_id, session.seed, session.delta, session.key,
                             t.scheme, t.block_gates)


def _fingerprint(link: Link) -> str:
    """The SHA-256 of the server's certificate (hex)."""
    identity = link.conn.identity
    return identity.fingerprint if identity is not None else ""


def _server(link: Link) -> str:
    """One server: its certificate and address (replicas may share a certificate)."""
    return f"{_fingerprint(link)}@{link.where}"


def _certificate(link: Link) -> bytes:
    """The server's certificate (DER) as this client's TLS session verified it."""
    transport = link.conn.transport
    ssl_object = transport.get_extra_info("ssl_object") if transport is not None else None
    return (ssl_object.getpeercert(binary_form=True) or b"") if ssl_object else b""
