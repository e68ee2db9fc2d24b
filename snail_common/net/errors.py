"""Errors of the wire protocol, with the machine-readable codes sent in ``error`` messages."""

from __future__ import annotations

# codes of ``error`` messages (the message text says what exactly was wrong)
MALFORMED = "malformed"  # not a msgpack map, wrong field type, duplicate key, ext type ...
OVERSIZE = "oversize"  # frame longer than the receiver's maximum
VERSION = "version"  # protocol version this build does not speak
UNKNOWN_TYPE = "unknown_type"
MISSING_FIELD = "missing_field"
UNKNOWN_FIELD = "unknown_field"
UNEXPECTED = "unexpected"  # a valid message this peer may not send here or now
FORBIDDEN = "forbidden"  # the peer's role may not do this, or dial that address
UNKNOWN_CIRCUIT = "unknown_circuit"
TOO_LARGE = "too_large"  # the circuit has more AND gates than this server compiles
CIRCUIT_MISMATCH = "circuit_mismatch"  # content hash differs between peers
BAD_REQUEST = "bad_request"  # well-formed but invalid values (delta parity, label count ...)
DUPLICATE_SESSION = "duplicate_session"
BUSY = "busy"  # max sessions reached
DRAINING = "draining"  # stopping (SIGTERM): finishes its sessions, takes no new ones
EVICTED = "evicted"  # a reservation (garbled ahead) whose place a live session took
TIMEOUT = "timeout"
PEER_LOST = "peer_lost"  # the other server went away mid-session
ABORTED = "aborted"  # cancelled by a peer
STREAM = "stream"  # the garbled-table stream does not fit the circuit
LINK = "link"  # a frame of the table data link fails its seal (datalink.py, seal.py)
TABLE_LINK = "table_link"  # garbler and evaluator were started with different --table-link
DIGEST = "digest"  # the tables received are not those the garbler signed (gc/attest.py)
REVOKED = "revoked"  # the peer certificate is listed in revoked.txt
SHUTDOWN = "shutdown"
INTERNAL = "internal"
# a session refused or lost for one of these may succeed on another replica at once
RETRYABLE = frozenset({BUSY, DRAINING, PEER_LOST, SHUTDOWN, TIMEOUT})
# the evaluator's codes for tables that reached it changed: the garbler's or the link's doing
TABLES_CHANGED = frozenset({LINK, DIGEST})


class ProtocolError(Exception):
    """A peer broke the protocol (or a request cannot be served): ``code`` is one of the
    codes above and goes on the wire with the message."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message

    def __str__(self) -> str:
        return f"{self.code}: {self.message}"


class RemoteError(Exception):
    """The peer sent an ``error`` message."""

    def __init__(self, code: str, message: str, sid: bytes | None = None) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message
        self.sid = sid


class ConnectionClosed(ConnectionError):
    """The peer closed the connection or it broke (EOF, reset, TLS failure)."""
