"""``snail-client health``, the TLS check behind the compose health checks, against real
daemons: healthy answers, and each way a server can look alive without being healthy."""

from __future__ import annotations

import json
import socket
import threading

import pytest
from click.testing import CliRunner

from snail_client.cli import main
from snail_common.net.tls import make_certs
from tests.daemons import daemons_with


@pytest.fixture(scope="module")
def services(tmp_path_factory):
    yield from daemons_with(tmp_path_factory)


def health(*args: str):
    return CliRunner().invoke(main, ["health", *args])


def test_client_reads_counters_of_both_servers(services):
    for role, addr in (("garbler", services.garbler_addr),
                       ("evaluator", services.evaluator_addr)):
        result = health(role, addr, "--tls-dir", str(services.tls_dir))
        assert result.exit_code == 0, result.output
        report = json.loads(result.stdout)
        assert report["role"] == role and report["answer"] == "health"
        assert report["tls"] == "TLSv1.3"
        assert report["uptime_s"] > 0 and "connections" in report["sessions"]


def test_server_probes_itself_with_its_own_certificate(services):
    result = health("garbler", services.garbler_addr, "--tls-dir", str(services.tls_dir),
                    "--as", "garbler")
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["answer"] == "forbidden" and report["as"] == "garbler"


def test_wrong_role_at_the_address_is_unhealthy(services):
    result = health("garbler", services.evaluator_addr, "--tls-dir", str(services.tls_dir))
    assert result.exit_code == 1
    assert "presents the certificate of evaluator" in result.stderr


def test_a_peer_the_server_refuses_is_unhealthy(services):
    # the garbler serves only clients; a refusal passes only for the server's own role
    result = health("garbler", services.garbler_addr, "--tls-dir", str(services.tls_dir),
                    "--as", "evaluator")
    assert result.exit_code == 1
    assert "forbidden" in result.stderr


def test_foreign_ca_is_unhealthy(services, tmp_path):
    foreign = make_certs(tmp_path / "foreign")
    result = health("evaluator", services.evaluator_addr, "--tls-dir", str(foreign))
    assert result.exit_code == 1
    assert "unhealthy" in result.stderr and "certificate" in result.stderr.lower()


def test_closed_port_is_unhealthy(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    tls_dir = make_certs(tmp_path / "tls")
    result = health("garbler", f"127.0.0.1:{port}", "--tls-dir", str(tls_dir))
    assert result.exit_code == 1
    assert "unhealthy" in result.stderr


def test_silent_listener_times_out(tmp_path):
    """A port that accepts TCP but never speaks TLS: what a bare connect check passes."""
    tls_dir = make_certs(tmp_path / "tls")
    with socket.socket() as srv:
        srv.bind(("127.0.0.1", 0))
        srv.listen()
        accepted: list[socket.socket] = []
        thread = threading.Thread(target=lambda: accepted.append(srv.accept()[0]))
        thread.start()
        result = health("garbler", f"127.0.0.1:{srv.getsockname()[1]}", "--tls-dir",
                        str(tls_dir), "--timeout", "0.5")
        thread.join()
        for conn in accepted:
            conn.close()
    assert result.exit_code == 1
    assert "within 0.5 s" in result.stderr


def test_missing_tls_files_exit_2(services, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    result = health("garbler", services.garbler_addr, "--tls-dir", str(empty))
    assert result.exit_code == 2
    assert "client.pem" in result.stderr


def test_bad_address_is_usage_error(tmp_path):
    result = health("garbler", "nowhere", "--tls-dir", str(tmp_path))
    assert result.exit_code == 2
    assert "HOST:PORT" in result.stderr
