"""Server-side timeouts: a silent connection with nothing under way is closed after
--idle-timeout; a frame, once begun, must arrive within --session-timeout."""

from __future__ import annotations

import contextlib
import socket
import ssl
import struct
import time

import numpy as np
import pytest
from daemons import daemons_with
from test_service_e2e import hello, raw, read_msg

from snail_client.blocking import SecureRunner
from snail_common.circuit import evaluate_bits, registry
from snail_common.net import errors
from snail_common.net import tls as tls_mod
from snail_common.net.conn import parse_addr


@pytest.fixture(scope="module")
def services(tmp_path_factory):
    yield from daemons_with(tmp_path_factory, "--idle-timeout", "1", "--session-timeout", "2",
                            "--handshake-timeout", "1")


@pytest.mark.parametrize("role", ["garbler", "evaluator"])
def test_a_silent_connection_is_closed_with_a_reason(services, role):
    addr = services.garbler_addr if role == "garbler" else services.evaluator_addr
    with contextlib.closing(raw(addr, services.tls_dir)) as sock:
        assert hello(sock)["t"] == "capabilities"
        reply = read_msg(sock)  # the socket's own 10 s timeout raises if none comes
        assert reply is not None and reply["code"] == errors.TIMEOUT and "idle" in reply["message"]
        assert read_msg(sock) is None  # then closed


def test_a_frame_announced_and_never_sent_loses_the_connection(services):
    with contextlib.closing(raw(services.evaluator_addr, services.tls_dir)) as sock:
        assert hello(sock)["t"] == "capabilities"
        sock.sendall(struct.pack(">I", 1 << 20) + b"x" * 100)
        # the server closes it: the end of the stream or a reset, never our socket's
        # 10 s timeout (TimeoutError is not suppressed)
        with contextlib.suppress(ConnectionError, ssl.SSLError):
            while read_msg(sock) is not None:
                pass


def test_a_client_idle_between_frames_reconnects(services):
    circuit = "ops/fmul-x4"
    _, schedule = registry.compiled(circuit)
    bits = np.random.default_rng(2).random(schedule.n_inputs) < 0.5
    with SecureRunner(services.garbler_addr, services.evaluator_addr, services.tls_dir,
                      timeout=30) as runner:
        want = evaluate_bits(schedule, bits[None])[0]
        np.testing.assert_array_equal(runner.run(circuit, bits), want)
        time.sleep(2.5)  # both servers close the idle links meanwhile
        np.testing.assert_array_equal(runner.run(circuit, bits), want)


@pytest.mark.parametrize("tls", [False, True], ids=["no TLS handshake", "no hello"])
def test_a_connection_that_stalls_before_hello_is_closed_after_the_handshake_timeout(
        services, tls):
    host, port = parse_addr(services.evaluator_addr)
    plain = socket.create_connection((host, port), timeout=10)
    sock = (tls_mod.client_context(services.tls_dir, "client")
            .wrap_socket(plain, server_hostname=host) if tls else plain)
    with contextlib.closing(sock):
        t0 = time.monotonic()
        # closed by the server (the end of the stream or a reset), never by our socket's
        # 10 s timeout (TimeoutError is not suppressed)
        with contextlib.suppress(ConnectionError, ssl.SSLError):
            while sock.recv(4096):
                pass
        took = time.monotonic() - t0
    assert took > 0.8, took  # not at once: after the 1 s handshake timeout (a bound that
    # holds at any speed: a timeout never fires early)
