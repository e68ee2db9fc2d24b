"""A blocking client's event loop does not run between calls, so a server that closed
its end meanwhile (restarted) is not seen by ``Connection.ended``; ``peer_closed`` reads
it off the socket, and the runner reconnects instead of failing its next run."""

from __future__ import annotations

import asyncio
import socket
import time

from snail_common.net.conn import Connection, new_event_loop


def test_a_close_while_the_loop_is_stopped_is_seen_by_peer_closed():
    loop = new_event_loop()
    listener = socket.create_server(("127.0.0.1", 0))
    try:
        port = listener.getsockname()[1]
        _, conn = loop.run_until_complete(
            loop.create_connection(Connection, "127.0.0.1", port))
        server_side, _ = listener.accept()
        assert not conn.peer_closed()  # open, nothing sent: alive
        server_side.close()
        time.sleep(0.1)  # the FIN arrives; the loop is not running to take it in
        assert not conn.ended
        assert conn.peer_closed()
        conn.transport.close()
        loop.run_until_complete(asyncio.sleep(0.01))
    finally:
        listener.close()
        loop.close()

