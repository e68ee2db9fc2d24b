"""One evaluator session: the state of an invocation from whichever half (the client's
labels or the garbler's stream) arrives first until it is done or failed."""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from typing import Any

from snail_common.gc.attest import TableDigest
from snail_common.gc.stream import DEFAULT_SCHEME
from snail_common.net.chunks import LabelAssembler
from snail_common.net.conn import Connection
from snail_common.net.errors import ProtocolError
from snail_common.net.slots import Slot

# largest circuit's inputs (n = 4096 points take about 10 MB), far below a memory risk
MAX_EARLY_LABEL_BYTES = 64 << 20


@dataclass(eq=False)
class Session:
    """One invocation, from whichever half arrives first until it is done or failed."""

    sid: bytes
    circuit: str
    hash: str
    ready: asyncio.Future  # the complete input labels, or the failure
    client: Connection | None = None
    garbler: bool = False
    labels: LabelAssembler | None = None
    failure: ProtocolError | None = None
    started: float = field(default_factory=time.monotonic)
    watchdog: asyncio.TimerHandle | None = None
    peer: str = ""  # the client's certificate name, once its half has arrived
    slot: Slot | None = None  # its place among the daemon's sessions
    n_and: int = 0
    bytes_in: int = 0
    bytes_out: int = 0
    queued: int = 0  # table bytes buffered while the labels are awaited
    scheme: str = DEFAULT_SCHEME  # as both halves declared it; the stream header must agree
    early: list[tuple[dict[str, Any], int]] = field(default_factory=list)  # labels that
    # came while the circuit was still loading, replayed once it is
    early_bytes: int = 0  # their wire size
    owner: LabelAssembler | None = None  # the map owner's wires, if the circuit has any
    # epoch seconds of the session's events here: first_received and last_received
    # (table frames), labels (the client's request complete), eval_end; tables_wait_s
    timeline: dict[str, float] = field(default_factory=dict)
    # the signed digest (attest.py): the garbler key the client named, the stream's
    # digest and header as fed, the garbler's tables_end, CPU seconds of the check
    signer: bytes | None = None
    digest: TableDigest = field(default_factory=TableDigest)
    head: bytes = b""
    tables_end: dict[str, Any] | None = None
    read_ahead: tuple[dict[str, Any], int] | None = None  # what came after the last frame
    block_gates: int = 0
    check_s: dict[str, float] = field(default_factory=lambda: {"digest_s": 0.0,
                                                                "verify_s": 0.0})

    def record(self, outcome: str, reason: str = "") -> dict:
        """This session's log line fields (see Daemon.log_session)."""
        return {"sid": self.sid, "circuit": self.circuit, "n_and": self.n_and,
                "bytes_in": self.bytes_in, "bytes_out": self.bytes_out,
                "seconds": time.monotonic() - self.started, "outcome": outcome,
                "reason": reason, "scheme": self.scheme, "timeline": self.timeline}


class StreamCut(Exception):
    """A session ended mid-stream for a reason of its own (its client, a timeout, an
    eviction, the garbler's ``error``): the stream itself is sound (tables.py)."""

    def __init__(self, garbler_ended: bool) -> None:
        super().__init__("the session ended before its stream")
        self.garbler_ended = garbler_ended  # the garbler's error {sid} ended it


def consume_failure(future: asyncio.Future) -> None:
    """Mark a failure as seen when no garbler half waits for it."""
    if not future.cancelled():
        future.exception()
