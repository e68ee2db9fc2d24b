"""The settings both daemons share, one field per command-line flag of the same name
(``net/cli.py`` makes the flags from these fields and their comments' defaults)."""

from __future__ import annotations

import os
from dataclasses import dataclass


@dataclass
class Options:
    """Daemon settings shared by garbler and evaluator (CLI flags of the same names)."""

    max_sessions: int = 64
    session_timeout: float = 30.0  # longest wait for a peer's next message mid-session
    handshake_timeout: float = 10.0
    grace: float = 10.0  # how long shutdown waits for running sessions
    workers: int = max(2, os.cpu_count() or 2)
    # largest circuit compiled or loaded: a daemon's memory peaks at ~200 bytes per AND
    # gate of it (n=256 SIL-LM: 15.2 M AND, 3.0 GB; 20-iteration DO at n=6: 12.6 M, 2.2 GB)
    max_and_gates: int = 40_000_000
    # garbled tables an evaluator holds for sessions whose client has not sent its labels
    # yet (garble-ahead); beyond this the garbler's streams wait
    ahead_bytes: int = 256 << 20
    ahead_bytes_per_peer: int = 128 << 20  # one client certificate name's share of it
    # sessions of one circuit starting within this window run as lanes of one pass
    # (garbler: requests; evaluator: client labels; 0: off), at most max_lanes at once; a
    # session waits for the window only while another run of its circuit is under way
    lane_window_ms: float = 10.0
    max_lanes: int = 16
    # a connection with no session and no message for this long is closed
    idle_timeout: float = 300.0
    # fairness between clients, by certificate name (clients sharing a certificate share
    # these); the garbler's links to the evaluator are not counted
    max_sessions_per_peer: int = 32
    # of those, sessions garbled ahead of need (reservations: net/slots.py): a client holds
    # up to 3 ahead, and those its runs have taken are reservations here until streamed
    max_ahead_per_peer: int = 8
    max_connections_per_peer: int = 64
    # how the garbler's tables travel to the evaluator (datalink.py), the same on both
    table_link: str = "aead"
    tls_dir: str | None = None  # where revoked.txt is read from (at start and on SIGHUP)
    metrics: tuple[str, int] | None = None  # HTTPS endpoint for /metrics and /health
