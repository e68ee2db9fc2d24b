"""The ``--metrics HOST:PORT`` endpoint: HTTPS GET of ``/metrics`` (Prometheus text) and
``/health`` (the health message as JSON), served from the daemon's counters.

TLS with the daemon's own certificate, as on every other link; no client certificate is
asked for, since the answers are counts an operator's scraper may read without holding a
snail role. Requests are bounded (8 KiB of header, 5 s) and answered once, then closed.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import ssl
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .tls import TLSFileError, cert_path, key_path

MAX_HEADER = 8 << 10
REQUEST_TIMEOUT = 5.0
PROMETHEUS_TYPE = "text/plain; version=0.0.4; charset=utf-8"


def scrape_context(tls_dir: str | Path, role: str) -> ssl.SSLContext:
    """Server side with the daemon's certificate; any client may connect."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    cert, key = cert_path(tls_dir, role), key_path(tls_dir, role)
    try:
        ctx.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        raise TLSFileError(f"TLS files {cert} and {key} cannot serve --metrics "
                           f"({getattr(exc, 'strerror', None) or exc})") from None
    return ctx


async def serve_scrapes(host: str, port: int, ctx: ssl.SSLContext,
                        prometheus: Callable[[], str],
                        health: Callable[[], dict[str, Any]]) -> asyncio.AbstractServer:
    """Start the endpoint; the caller closes the returned server."""

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), REQUEST_TIMEOUT)
            status, kind, body = _answer(head, prometheus, health)
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError,
                asyncio.TimeoutError, ConnectionError, ssl.SSLError):
            writer.close()
            return
        writer.write(f"HTTP/1.1 {status}\r\nContent-Type: {kind}\r\n"
                     f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n".encode()
                     + body)
        with contextlib.suppress(ConnectionError, ssl.SSLError):
            await writer.drain()
        writer.close()

    return await asyncio.start_server(handle, host, port, ssl=ctx, limit=MAX_HEADER,
                                      ssl_handshake_timeout=REQUEST_TIMEOUT)


def _answer(head: bytes, prometheus: Callable[[], str],
            health: Callable[[], dict[str, Any]]) -> tuple[str, str, bytes]:
    parts = head.split(b"\r\n", 1)[0].split()
    if len(parts) != 3 or parts[0] != b"GET":
        return "405 Method Not Allowed", "text/plain", b"only GET /metrics or /health\n"
    path = parts[1].split(b"?", 1)[0]
    if path == b"/metrics":
        return "200 OK", PROMETHEUS_TYPE, prometheus().encode()
    if path == b"/health":
        return "200 OK", "application/json", json.dumps(health()).encode() + b"\n"
    return "404 Not Found", "text/plain", b"try /metrics or /health\n"

