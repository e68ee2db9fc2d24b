"""Certificates: one CA, one certificate per role, roles readable from a verified peer."""

import contextlib
import ipaddress
import ssl
import stat

import pytest
from click.testing import CliRunner
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding

from snail_client.cli import main
from snail_common.net import tls


@pytest.fixture(scope="module")
def tls_dir(tmp_path_factory):
    return tls.make_certs(tmp_path_factory.mktemp("tls"), hosts=["garbler", "10.0.0.7"])


def load(tls_dir, name) -> x509.Certificate:
    return x509.load_pem_x509_certificate(tls.cert_path(tls_dir, name).read_bytes())


def test_files_and_key_permissions(tls_dir):
    for name in ("ca", "garbler", "evaluator", "client"):
        assert tls.cert_path(tls_dir, name).is_file()
        assert stat.S_IMODE(tls.key_path(tls_dir, name).stat().st_mode) == 0o600


def test_server_names_include_loopback_and_extra_hosts(tls_dir):
    san = load(tls_dir, "garbler").extensions.get_extension_for_class(
        x509.SubjectAlternativeName).value
    assert {"localhost", "garbler"} <= set(san.get_values_for_type(x509.DNSName))
    assert {ipaddress.ip_address("127.0.0.1"), ipaddress.ip_address("10.0.0.7")} <= set(
        san.get_values_for_type(x509.IPAddress))


def test_contexts_are_tls13_only_with_mutual_auth(tls_dir):
    server = tls.server_context(tls_dir, "evaluator")
    client = tls.client_context(tls_dir, "client")
    for ctx in (server, client):
        assert ctx.minimum_version == ctx.maximum_version == ssl.TLSVersion.TLSv1_3
        assert ctx.verify_mode == ssl.CERT_REQUIRED
    assert client.check_hostname


@pytest.mark.parametrize("role", ["garbler", "evaluator", "client"])
def test_peer_role_comes_from_the_verified_certificate(tls_dir, role):
    server = tls.server_context(tls_dir, "evaluator")
    client = tls.client_context(tls_dir, role)
    c_in, c_out, s_in, s_out = (ssl.MemoryBIO() for _ in range(4))
    c = client.wrap_bio(c_in, c_out, server_hostname="localhost")
    s = server.wrap_bio(s_in, s_out, server_side=True)
    for _ in range(6):  # handshake over memory BIOs
        for side in (c, s):
            with contextlib.suppress(ssl.SSLWantReadError):
                side.do_handshake()
        s_in.write(c_out.read())
        c_in.write(s_out.read())
    assert tls.peer_identity(s).role == role
    assert tls.peer_identity(c).role == "evaluator"


def test_missing_files_are_named(tmp_path):
    with pytest.raises(tls.TLSFileError, match=r"garbler\.pem is missing"):
        tls.server_context(tmp_path, "garbler")
    with pytest.raises(ValueError, match="role"):
        tls.server_context(tmp_path, "mallory")


def test_certs_command(tmp_path):
    out = tmp_path / "certs"
    result = CliRunner().invoke(main, ["certs", str(out), "--host", "evaluator"])
    assert result.exit_code == 0, result.output
    assert tls.cert_path(out, "client").is_file()
    again = CliRunner().invoke(main, ["certs", str(out)])
    assert again.exit_code == 2 and "already holds keys" in again.output


# found by the certificates fuzz target once it patched valid DER (``_patched``): each was
# a cryptography exception other than TLSFileError out of ``snail-client certs --client``
def _subject_offset(pem: bytes) -> int:
    cert = x509.load_pem_x509_certificate(pem)
    # a self-signed CA: the issuer (parsed at once) has the same bytes, and comes first
    return cert.public_bytes(Encoding.DER).rindex(cert.subject.public_bytes())


@pytest.mark.parametrize(("where", "what"), [
    (lambda pem: 12, "not a valid X509 version"),  # InvalidVersion is no ValueError
    (_subject_offset, "subject"),  # the subject is parsed lazily, on first use
])
def test_a_damaged_ca_certificate_is_a_named_error_when_issuing(tmp_path, where, what):
    from snail_bench.fuzz_targets import _patched

    folder = tls.make_certs(tmp_path / "tls")
    ca = folder / "ca.pem"
    pem = ca.read_bytes()
    ca.write_bytes(_patched(pem, where(pem).to_bytes(2, "little") + b"\x01"))
    with pytest.raises(tls.TLSFileError, match=f"holds no usable CA.*{what}"):
        tls.add_client(folder, "robot")


def test_a_ca_key_of_another_ca_is_refused_when_issuing(tmp_path):
    folder = tls.make_certs(tmp_path / "tls")
    other = tls.make_certs(tmp_path / "other")
    (folder / "ca.key").write_bytes((other / "ca.key").read_bytes())
    with pytest.raises(tls.TLSFileError, match="do not belong together"):
        tls.add_client(folder, "robot")
