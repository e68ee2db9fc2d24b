"""``snail-client health``: is a garbler or evaluator up? Asked over mutual TLS 1.3.

A TCP connect only shows that something listens; this check opens the protocol as a real
peer would: TLS 1.3 with certificates on both ends (the server's must be ROLE's, from the
same CA), then ``hello``. A peer the server serves (the client; the garbler at the
evaluator) gets ``capabilities`` and then the server's ``health`` counters. A server probed
from its own container holds only its own certificate, which a daemon does not serve: the
check then passes on the daemon's ``forbidden`` answer to that hello, which shows the
listener, its certificate and its event loop all work, but gives no counters.

Exit status: 0 healthy (one JSON line on stdout), 1 unhealthy (one line on stderr says
why), 2 bad usage or TLS files.
"""

from __future__ import annotations

import asyncio
import json
import ssl
import sys
from typing import Any

import click

from snail_common.net import messages, tls
from snail_common.net.conn import SOFTWARE, Connection, format_addr, new_event_loop, parse_addr
from snail_common.net.errors import FORBIDDEN, ConnectionClosed, ProtocolError
from snail_common.net.frames import MAX_FRAME

SERVERS = ("garbler", "evaluator")


class Unhealthy(Exception):
    """The server did not answer as a healthy one does; the message says what happened."""


async def probe(host: str, port: int, role: str, tls_dir: str, as_role: str,
                timeout: float) -> dict[str, Any]:
    """Open the protocol with the ``role`` server at host:port as ``as_role``; its health
    report, or what shows it alive when it does not serve ``as_role``. Raises Unhealthy."""
    where = f"the {role} at {format_addr(host, port)}"
    ctx = tls.client_context(tls_dir, as_role)
    loop = asyncio.get_running_loop()
    try:
        transport, conn = await asyncio.wait_for(loop.create_connection(
            lambda: Connection(MAX_FRAME), host, port, ssl=ctx, server_hostname=host,
            ssl_handshake_timeout=timeout), timeout)
    except (asyncio.TimeoutError, TimeoutError):
        raise Unhealthy(f"{where}: no TLS connection within {timeout:g} s") from None
    except (OSError, ssl.SSLError) as exc:
        raise Unhealthy(f"{where}: {exc}") from None
    version = transport.get_extra_info("ssl_object").version()
    try:
        if conn.peer_role != role:
            raise Unhealthy(f"{where} presents the certificate of "
                            f"{conn.peer_role or 'no snail role'}")
        report: dict[str, Any] = {"role": role, "address": format_addr(host, port),
                                  "tls": version, "as": as_role}
        # a server that refuses the certificate answers and closes without reading the
        # hello: post it (the write may find the stream closed) and read the answer
        conn.post(messages.make("hello", role=as_role, software=SOFTWARE,
                                max_frame=MAX_FRAME))
        reply, _ = await conn.recv(timeout)
        if reply["t"] == "error" and reply["code"] == FORBIDDEN and as_role == role:
            return {**report, "answer": "forbidden", "message": reply["message"]}
        if reply["t"] != "capabilities":
            raise Unhealthy(f"{where} answered hello with {_describe(reply)}")
        conn.write(messages.make("health_request"))
        health, _ = await conn.recv(timeout)
        if health["t"] != "health":
            raise Unhealthy(f"{where} answered health_request with {_describe(health)}")
        return {**report, "answer": "health", "software": reply["software"],
                "sessions": health["sessions"], "uptime_s": health["uptime_s"]}
    except TimeoutError:
        raise Unhealthy(f"{where}: no answer within {timeout:g} s") from None
    except (ConnectionClosed, ProtocolError) as exc:
        raise Unhealthy(f"{where}: {exc}") from None
    finally:
        await conn.close(messages.make("bye"), timeout=1.0)


def _describe(msg: dict[str, Any]) -> str:
    if msg["t"] == "error":
        return f"error {msg['code']}: {msg['message']}"
    return msg["t"]


@click.command("health")
@click.argument("role", type=click.Choice(SERVERS))
@click.argument("address", metavar="HOST:PORT")
@click.option("--tls-dir", required=True, type=click.Path(file_okay=False, exists=True),
              help="Directory with ca.pem and the certificate and key of --as.")
@click.option("--as", "as_role", type=click.Choice(["client", *SERVERS]), default="client",
              show_default=True,
              help="Whose certificate to connect with. A server checking itself (a "
                   "container health check) passes its own role: it gets no counters.")
@click.option("--timeout", type=click.FloatRange(0.1, 600), default=5.0, show_default=True,
              metavar="SECONDS", help="Limit for the connection and for each answer.")
def health_cmd(role: str, address: str, tls_dir: str, as_role: str, timeout: float) -> None:
    """Check that the ROLE server at HOST:PORT answers over mutual TLS 1.3.

    Prints one JSON line (the server's session counters and uptime when --as is a peer it
    serves) and exits 0; exits 1 with the reason on stderr when the server is down, slow,
    presents another certificate or answers wrongly; 2 for bad usage or TLS files.
    """
    try:
        host, port = parse_addr(address)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="HOST:PORT") from None
    loop = new_event_loop()
    try:
        report = loop.run_until_complete(probe(host, port, role, tls_dir, as_role, timeout))
    except tls.TLSFileError as exc:
        _fail(2, f"--tls-dir: {exc}")
    except Unhealthy as exc:
        _fail(1, f"unhealthy: {exc}")
    finally:
        loop.close()
    click.echo(json.dumps(report))


def _fail(code: int, message: str) -> None:
    click.echo(f"snail-client health: {message}", err=True)
    sys.exit(code)
