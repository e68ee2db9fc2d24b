"""The garbler dials only the map owners its operator allowed (``--map-owner``, a name
resolved to its addresses): a client naming another address, or any address when none is
allowed, is refused as ``forbidden``, and the garbler opens no connection to it (a client
must not make the server dial where it likes). The end-to-end allowed case is the
map-owner end-to-end tests (test_mapowner_e2e.py)."""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys

import numpy as np
import pytest

from snail_client.blocking import SecureRunner
from snail_client.embedded import start_daemon
from snail_client.links import ServiceError
from snail_common.circuit import registry
from snail_common.net import errors
from snail_common.net.replicas import address_key
from snail_common.net.tls import make_certs

CIRCUIT = "loc/lm-sil-ldlt-n4-mo"  # the smallest map-owner circuit
NOT_ALLOWED = "the operator must allow it (--map-owner on the garbler)"


class Listener:
    """A TCP socket on loopback that nobody should dial; counts who did. The kernel
    completes a connection to a listening socket before anyone accepts it, so a dial that
    happened is found by a non-blocking accept afterwards."""

    def __init__(self) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.port = self.sock.getsockname()[1]
        self.accepted: list[socket.socket] = []

    def dialled(self) -> int:
        with contextlib.suppress(BlockingIOError):
            while True:
                self.accepted.append(self.sock.accept()[0])
        return len(self.accepted)

    def close(self) -> None:
        for conn in [*self.accepted, self.sock]:
            conn.close()


@pytest.fixture(scope="module")
def listener():
    target = Listener()
    yield target
    target.close()


@pytest.fixture(scope="module")
def tls_dir(tmp_path_factory):
    return make_certs(tmp_path_factory.mktemp("tls"))


@pytest.fixture(scope="module")
def evaluator(tmp_path_factory, tls_dir):
    daemon = start_daemon("evaluator", ["--tls-dir", str(tls_dir)],
                          tmp_path_factory.mktemp("evaluator") / "evaluator.log")
    yield daemon
    daemon.stop()


@contextlib.contextmanager
def garbler(tmp_path, tls_dir, evaluator, *flags: str):
    daemon = start_daemon("garbler", ["--evaluator", evaluator.address, "--tls-dir",
                                      str(tls_dir), *flags], tmp_path / "garbler.log")
    try:
        yield daemon
    finally:
        daemon.stop()


def request_map_owner(garbler, evaluator, tls_dir, map_owner: str) -> ServiceError:
    """One run of a map-owner circuit whose request names ``map_owner``; its failure."""
    bits = np.zeros(registry.interface(CIRCUIT).n_inputs, bool)
    with SecureRunner(garbler.address, evaluator.address, tls_dir, timeout=120) as runner:
        runner.use_frame(bytes(16), map_owner)
        with pytest.raises(ServiceError) as failed:
            runner.run(CIRCUIT, bits)
    return failed.value


@pytest.mark.parametrize("allowed, named, words", [
    ((), "127.0.0.1:{port}", "none is allowed"),
    (("127.0.0.2:{port}",), "127.0.0.1:{port}",
     "127.0.0.1:{port} is not a map owner this server may dial"),
    # a client's host name is compared with the operator's names, never resolved
    (("127.0.0.1:{port}",), "localhost:{port}",
     "localhost:{port} is not a map owner this server may dial"),
], ids=["none_allowed", "another_allowed", "client_name_not_resolved"])
def test_a_map_owner_not_allowed_is_refused_and_never_dialled(tmp_path, tls_dir, evaluator,
                                                              listener, allowed, named,
                                                              words):
    flags = [arg for addr in allowed
             for arg in ("--map-owner", addr.format(port=listener.port))]
    named = named.format(port=listener.port)
    with garbler(tmp_path, tls_dir, evaluator, *flags) as daemon:
        error = request_map_owner(daemon, evaluator, tls_dir, named)
        assert error.code == errors.FORBIDDEN
        assert "field 'map_owner'" in str(error)
        assert words.format(port=listener.port) in str(error)
        assert listener.dialled() == 0
        # the garbler serves on: the next client is refused the same way
        error = request_map_owner(daemon, evaluator, tls_dir, named)
        assert error.code == errors.FORBIDDEN and listener.dialled() == 0


def test_a_map_owner_allowed_by_name_is_reached_at_the_address_it_resolves_to(
        tmp_path, tls_dir, evaluator, listener):
    """The operator names the map owner (``localhost``, as a service name); a client that
    reached it at one of the addresses the name resolves to may name that address."""
    with garbler(tmp_path, tls_dir, evaluator, "--map-owner",
                 f"localhost:{listener.port}") as daemon:
        error = request_map_owner(daemon, evaluator, tls_dir, f"127.0.0.1:{listener.port}")
        # dialled: the listener is no map owner, so the TLS opening fails after it
        assert error.code == errors.PEER_LOST and "map owner" in str(error)
        assert listener.dialled() == 1


def test_addresses_are_compared_after_parsing():
    assert address_key(("::1", 7001)) == address_key(("0:0::1", 7001))
    assert address_key(("Map.Example.ORG", 7001)) == ("map.example.org", 7001)
    assert address_key(("127.0.0.1", 7001)) != address_key(("127.0.0.1", 7002))
    assert address_key(("localhost", 7001)) != address_key(("127.0.0.1", 7001))


def garbler_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "snail_garbler", *args],
                          capture_output=True, text=True, timeout=60)


def test_a_bad_map_owner_address_is_exit_2_naming_the_option(tls_dir):
    out = garbler_cli("--listen", "127.0.0.1:0", "--evaluator", "127.0.0.1:1",
                      "--tls-dir", str(tls_dir), "--map-owner", "127.0.0.1:7003",
                      "--map-owner", "bad")
    assert out.returncode == 2
    assert "--map-owner" in out.stderr and "'bad'" in out.stderr
    assert "Traceback" not in out.stderr


def test_help_says_why_and_how_to_name_a_map_owner():
    out = garbler_cli("--help")
    assert out.returncode == 0
    text = " ".join(out.stdout.split())
    assert "--map-owner HOST:PORT" in text and "(repeatable)" in text
    assert "no client can make it connect wherever it likes" in text
    assert "map-owner sessions are refused" in text
    assert "a client's own host name is compared, never resolved" in text
