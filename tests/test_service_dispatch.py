"""How each daemon ends a served connection (service.Daemon.serve, serving, ends_link):
the peer's certificate role picks the loop; on every link a health request is answered
and a bye ends it; any other message is refused as unexpected, logged, and the
connection closed with that error; a peer that leaves is logged. The real daemons run
here on in-memory connections, so each role's refusal text and log line are pinned."""

import asyncio
import logging

import numpy as np
import pytest

from snail_common.net import messages
from snail_common.net.errors import ABORTED, UNEXPECTED, ConnectionClosed
from snail_common.net.service import Options
from snail_evaluator.daemon import EvaluatorDaemon
from snail_garbler.daemon import GarblerDaemon
from snail_mapd.daemon import MapOwnerDaemon

# (daemon, peer role, what that peer hears when it sends tables outside its protocol)
REFUSALS = [
    ("garbler", "client", "a client may not send tables to the garbler"),
    ("evaluator", "client", "a client may not send tables to the evaluator"),
    ("evaluator", "mapowner", "the map owner may not send tables to the evaluator"),
    ("evaluator", "garbler", "the garbler sent tables outside a session"),
    ("mapowner", "client", "a client may not send tables to the map owner"),
    ("mapowner", "garbler", "the garbler may not send tables to the map owner"),
]
ROLES = [(daemon, peer) for daemon, peer, _ in REFUSALS]
HANG_UP = "the peer hung up"


class Link:
    """A served connection's stand-in: what its peer sends, what the daemon answers."""

    def __init__(self, role: str, *incoming: dict) -> None:
        self.peer_role, self.peer_name, self.peer = role, f"a-{role}", ("127.0.0.1", 4242)
        self.incoming = list(incoming)
        self.sent: list[dict] = []
        self.last: dict | None = None  # the frame the daemon closed the connection with
        self.posted: list[dict | None] = []  # notices and the closing frame, in order

    async def recv(self, timeout: float | None = None) -> tuple[dict, int]:
        await asyncio.sleep(0)  # what the daemon started meanwhile runs, as on a network
        if not self.incoming:
            raise ConnectionClosed(HANG_UP)
        return self.incoming.pop(0), 16

    async def send(self, msg: dict) -> int:
        self.sent.append(msg)
        return 16

    def post(self, msg: dict) -> None:
        self.posted.append(msg)

    async def close(self, last: dict | None = None, timeout: float = 2.0) -> None:
        self.last = last
        self.posted.append(last)


class Lines(logging.Handler):
    """The daemon's structured log lines: (event, level, fields)."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.lines: list[tuple[str, int, dict]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append((record.getMessage(), record.levelno,
                           getattr(record, "snail_fields", {})))


@pytest.fixture
def lines():
    logger = logging.getLogger("snail.test_dispatch")
    logger.setLevel(logging.DEBUG)
    handler = Lines()
    logger.addHandler(handler)
    yield handler.lines
    logger.removeHandler(handler)


def serve(role: str, link: Link, stuck: bool = False) -> None:
    """Serve ``link`` on a fresh ``role`` daemon (``stuck``: its circuits never load)."""
    logger = logging.getLogger("snail.test_dispatch")
    daemon = {
        "garbler": lambda: GarblerDaemon(Options(workers=1), logger, (("127.0.0.1", 1),), None,
                                         ()),
        "evaluator": lambda: EvaluatorDaemon(Options(workers=1), logger),
        "mapowner": lambda: MapOwnerDaemon(Options(workers=1), logger, None,
                                           np.zeros((1, 1), np.uint8), None),
    }[role]()
    if stuck:
        async def never(*_args):
            await asyncio.Event().wait()

        daemon.circuit = never
    try:
        asyncio.run(daemon.serve(link))
    finally:
        daemon.pool.shutdown()


@pytest.mark.parametrize(("daemon", "peer", "refusal"), REFUSALS)
def test_an_unexpected_message_closes_the_link_with_an_error_naming_it(daemon, peer,
                                                                       refusal, lines):
    link = Link(peer, {"t": "tables"}, {"t": "bye"})
    serve(daemon, link)
    assert link.last == messages.error(UNEXPECTED, refusal)
    assert link.incoming == [{"t": "bye"}], "the loop went on after the refusal"
    event, level, fields = lines[-1]
    assert (event, level) == ("protocol_error", logging.WARNING)
    assert fields["peer"] == link.peer_name and fields["address"] == str(link.peer)
    assert (fields["code"], fields["reason"]) == (UNEXPECTED, refusal)


@pytest.mark.parametrize(("daemon", "peer"), ROLES)
def test_every_link_answers_health_and_ends_at_bye(daemon, peer, lines):
    link = Link(peer, {"t": "health_request"}, {"t": "bye"}, {"t": "tables"})
    serve(daemon, link)
    assert [(m["t"], m["role"]) for m in link.sent] == [("health", daemon)]
    assert link.last is None and link.incoming == [{"t": "tables"}]
    assert not [line for line in lines if line[1] >= logging.WARNING]


@pytest.mark.parametrize(("daemon", "peer"), ROLES)
def test_a_peer_that_leaves_is_logged_not_answered(daemon, peer, lines):
    link = Link(peer)
    serve(daemon, link)
    assert link.last is None and link.sent == []
    gone = "client_gone" if daemon == "garbler" else "peer_gone"
    assert [(e, lv, f["peer"], f["reason"]) for e, lv, f in lines] == [
        (gone, logging.INFO, link.peer_name, HANG_UP)]


def test_the_garbler_closes_a_broken_link_before_it_ends_the_links_sessions(lines):
    """The client hears why its connection was closed, not that it left: the garbler's
    sessions are cancelled once the error has gone out (so their notices go nowhere)."""
    sid = bytes(range(16))
    request = {"t": "garble_request", "sid": sid, "circuit": "ops/fadd-x1", "hash": "0" * 64}
    link = Link("client", request, {"t": "tables"})
    serve("garbler", link, stuck=True)
    refusal = "a client may not send tables to the garbler"
    assert link.posted == [messages.error(UNEXPECTED, refusal),
                           messages.error(ABORTED, "the client disconnected", sid)]
    assert [(e, f.get("outcome")) for e, _, f in lines] == [("protocol_error", None),
                                                           ("session", ABORTED)]
