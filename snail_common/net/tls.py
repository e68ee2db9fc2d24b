"""TLS 1.3 with mutual authentication on every link, and the role of a peer from its cert.

``make_certs(dir)`` writes a private CA and one certificate per role (EC P-256 keys):

    ca.pem ca.key  garbler.pem garbler.key  evaluator.pem evaluator.key  client.pem client.key

The role is the certificate's common name (``snail garbler`` etc. under organization
``snail``); only certificates signed by the CA are accepted, so a peer cannot claim a role
it has no certificate for. ``add_client(dir, name)`` issues a further client certificate
``name.pem``/``name.key`` whose organizational unit carries the name: daemons log it, count
quotas by it and refuse it once ``revoked.txt`` in their TLS directory lists it (by name
or SHA-256 fingerprint; reloaded on SIGHUP).

Servers require a client certificate; clients verify the server name against the SAN
(localhost, 127.0.0.1, ::1 and any extra hosts) and check that the server has the role
they meant to reach, so a client never sends its seed to the evaluator by a swapped
address.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import ipaddress
import os
import re
import ssl
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from .messages import ROLES

CA = "ca"
_ORG = "snail"
_PREFIX = "snail "
VALID_DAYS = 365
DEFAULT_HOSTS = ("localhost", "127.0.0.1", "::1")
REVOKED = "revoked.txt"
CLIENT_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")


def cert_path(tls_dir: str | Path, name: str) -> Path:
    return Path(tls_dir) / f"{name}.pem"


def key_path(tls_dir: str | Path, name: str) -> Path:
    return Path(tls_dir) / f"{name}.key"


def _name(common: str, unit: str | None = None) -> x509.Name:
    attributes = [x509.NameAttribute(NameOID.ORGANIZATION_NAME, _ORG)]
    if unit is not None:
        attributes.append(x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, unit))
    return x509.Name([*attributes, x509.NameAttribute(NameOID.COMMON_NAME, common)])


def _san(hosts: Iterable[str]) -> x509.SubjectAlternativeName:
    names: list[x509.GeneralName] = []
    for host in dict.fromkeys(hosts):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return x509.SubjectAlternativeName(names)


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def _builder(subject: x509.Name, issuer: x509.Name, key: ec.EllipticCurvePrivateKey,
             days: int) -> x509.CertificateBuilder:
    now = dt.datetime.now(dt.timezone.utc)
    return (x509.CertificateBuilder().subject_name(subject).issuer_name(issuer)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=days)))


def make_certs(directory: str | Path, hosts: Iterable[str] = (),
               days: int = VALID_DAYS) -> Path:
    """Create a CA and certificates for garbler, evaluator and client in ``directory``.

    ``hosts`` are extra DNS names or IP addresses the servers are reached by (e.g. the
    compose service names). Keys are written with mode 0600; keep ``ca.key`` off the
    servers in a real deployment (it is only needed to issue more certificates).
    """
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = _name("snail CA")
    ca_cert = (_builder(ca_name, ca_name, ca_key, days)
               .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
               .add_extension(x509.KeyUsage(False, False, False, False, False, True, True,
                                            False, False), critical=True)
               .sign(ca_key, hashes.SHA256()))
    _write_key(key_path(out, CA), ca_key)
    cert_path(out, CA).write_bytes(ca_cert.public_bytes(serialization.Encoding.PEM))
    san = _san([*DEFAULT_HOSTS, *hosts])
    for role in ROLES:
        _issue(out, role, role, None, ca_key, ca_name, days,
               san if role != "client" else None)
    return out


def _issue(out: Path, file_name: str, role: str, unit: str | None,
           ca_key: ec.EllipticCurvePrivateKey, ca_name: x509.Name, days: int,
           san: x509.SubjectAlternativeName | None) -> None:
    key = ec.generate_private_key(ec.SECP256R1())
    usages = [ExtendedKeyUsageOID.CLIENT_AUTH]
    if san is not None:  # servers; the garbler is also a client of the evaluator
        usages.append(ExtendedKeyUsageOID.SERVER_AUTH)
    builder = (_builder(_name(_PREFIX + role, unit), ca_name, key, days)
               .add_extension(x509.BasicConstraints(ca=False, path_length=None),
                              critical=True)
               .add_extension(x509.ExtendedKeyUsage(usages), critical=False))
    if san is not None:
        builder = builder.add_extension(san, critical=False)
    cert = builder.sign(ca_key, hashes.SHA256())
    _write_key(key_path(out, file_name), key)
    cert_path(out, file_name).write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def add_client(directory: str | Path, name: str, days: int = VALID_DAYS) -> Path:
    """Issue client certificate ``name`` (``name.pem``/``name.key``) with the CA kept in
    ``directory``: one per device, so that each can be told apart and revoked."""
    out = Path(directory)
    if not CLIENT_NAME.fullmatch(name) or name in (*ROLES, CA):
        raise ValueError(f"client name {name!r}: use 1-64 letters, digits, '.', '_' or '-', "
                         f"not one of {', '.join((*ROLES, CA))}")
    if cert_path(out, name).exists() or key_path(out, name).exists():
        raise ValueError(f"{cert_path(out, name)} already exists: choose another name")
    try:
        ca_key = serialization.load_pem_private_key(key_path(out, CA).read_bytes(), None)
        ca_cert = x509.load_pem_x509_certificate(cert_path(out, CA).read_bytes())
        ca_name = ca_cert.subject  # parsed lazily: a damaged name fails here
        ca_public = ca_cert.public_key()
    except (OSError, ValueError, UnsupportedAlgorithm, x509.InvalidVersion) as exc:
        raise TLSFileError(f"{out} holds no usable CA (ca.pem and ca.key: "
                           f"{getattr(exc, 'strerror', None) or exc}; {_REMEDY})") from None
    if not isinstance(ca_key, ec.EllipticCurvePrivateKey):
        raise TLSFileError(f"{key_path(out, CA)} is not an EC key made by snail-client certs")
    if _public_der(ca_public) != _public_der(ca_key.public_key()):
        raise TLSFileError(f"{cert_path(out, CA)} and {key_path(out, CA)} do not belong "
                           f"together: certificates issued with them would not verify "
                           f"({_REMEDY})")
    _issue(out, name, "client", name, ca_key, ca_name, days, None)
    return cert_path(out, name)


def _public_der(key: ec.EllipticCurvePublicKey) -> bytes:
    return key.public_bytes(serialization.Encoding.DER,
                            serialization.PublicFormat.SubjectPublicKeyInfo)


class TLSFileError(ValueError):
    """A certificate or key file is missing, unreadable or not what it should be; the
    message names the file and what to do."""


_REMEDY = "create the directory with 'snail-client certs DIR'"


def _context(purpose: int, tls_dir: str | Path, role: str,
             name: str | None = None) -> ssl.SSLContext:
    if role not in ROLES:
        raise ValueError(f"role must be one of {ROLES}, got {role!r}")
    name = name or role
    cert, key, ca = cert_path(tls_dir, name), key_path(tls_dir, name), cert_path(tls_dir, CA)
    for path in (cert, key, ca):
        if not path.is_file():
            raise TLSFileError(f"TLS file {path} is missing ({_REMEDY})")
    ctx = ssl.SSLContext(purpose)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_3
    ctx.maximum_version = ssl.TLSVersion.TLSv1_3
    try:
        ctx.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        raise TLSFileError(f"TLS files {cert} and {key} cannot be used as the {role}'s "
                           f"certificate and key ({exc.strerror or exc}; {_REMEDY})") from None
    try:
        ctx.load_verify_locations(ca)
    except (OSError, ssl.SSLError) as exc:
        raise TLSFileError(f"TLS file {ca} cannot be used as the CA certificate "
                           f"({exc.strerror or exc}; {_REMEDY})") from None
    ctx.verify_mode = ssl.CERT_REQUIRED
    return ctx


def server_context(tls_dir: str | Path, role: str) -> ssl.SSLContext:
    """Server side of ``role``: TLS 1.3 only, client certificate required."""
    return _context(ssl.PROTOCOL_TLS_SERVER, tls_dir, role)


def client_context(tls_dir: str | Path, role: str, name: str | None = None) -> ssl.SSLContext:
    """Connecting side of ``role`` with certificate ``name`` (default: the role's own):
    TLS 1.3 only, server name and chain checked."""
    ctx = _context(ssl.PROTOCOL_TLS_CLIENT, tls_dir, role, name)
    ctx.check_hostname = True
    return ctx


@dataclass(frozen=True)
class Identity:
    """Who a verified peer is: its role, its name (a client's own name, else the role)
    and the SHA-256 fingerprint of its certificate (hex)."""

    role: str
    name: str
    fingerprint: str

    def revoked_by(self, revoked: frozenset[str]) -> bool:
        return self.name in revoked or self.fingerprint in revoked


def peer_identity(ssl_object: ssl.SSLObject | ssl.SSLSocket | None) -> Identity:
    """The identity in the verified peer certificate; ValueError if there is none."""
    cert = ssl_object.getpeercert() if ssl_object is not None else None
    if not cert:
        raise ValueError("the peer presented no verified certificate")
    subject = {k: v for rdn in cert.get("subject", ()) for k, v in rdn}
    common = subject.get("commonName", "")
    role = common[len(_PREFIX):] if common.startswith(_PREFIX) else ""
    if subject.get("organizationName") != _ORG or role not in ROLES:
        raise ValueError(f"the peer certificate names no snail role (subject {subject})")
    der = ssl_object.getpeercert(binary_form=True) or b""
    return Identity(role, subject.get("organizationalUnitName", role),
                    hashlib.sha256(der).hexdigest())


def read_revoked(tls_dir: str | Path) -> frozenset[str]:
    """Names and fingerprints listed in ``tls_dir/revoked.txt`` (one a line, ``#``
    comments; fingerprints in hex, colons allowed); none if the file does not exist."""
    path = Path(tls_dir) / REVOKED
    try:
        text = path.read_text()
    except FileNotFoundError:
        return frozenset()
    except (OSError, UnicodeDecodeError) as exc:
        raise TLSFileError(f"{path} cannot be read ({exc})") from None
    entries = (line.split("#", 1)[0].strip() for line in text.splitlines())
    return frozenset(_normalized(e) for e in entries if e)


def _normalized(entry: str) -> str:
    """Fingerprints compare as lowercase hex without colons; names as written."""
    bare = entry.replace(":", "").lower()
    return bare if re.fullmatch(r"[0-9a-f]{64}", bare) else entry


def endorse(tls_dir: str | Path, name: str, message: bytes) -> bytes:
    """``message`` signed (ECDSA, SHA-256) with the key of certificate ``name`` in
    ``tls_dir``: how a garbler binds its Ed25519 signing key to its certificate, so that
    a third party holding only the certificate can tell whose signatures they are."""
    path = key_path(tls_dir, name)
    try:
        key = serialization.load_pem_private_key(path.read_bytes(), None)
    except (OSError, ValueError, UnsupportedAlgorithm) as exc:
        raise TLSFileError(f"TLS file {path} cannot be read as a key "
                           f"({getattr(exc, 'strerror', None) or exc}; {_REMEDY})") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise TLSFileError(f"{path} is not an EC key made by snail-client certs")
    return key.sign(message, ec.ECDSA(hashes.SHA256()))


def endorsed(cert_der: bytes, message: bytes, signature: bytes) -> bool:
    """Whether the key of the certificate ``cert_der`` signed ``message`` (``endorse``)."""
    try:
        public = x509.load_der_x509_certificate(cert_der).public_key()
        if not isinstance(public, ec.EllipticCurvePublicKey):
            return False
        public.verify(signature, message, ec.ECDSA(hashes.SHA256()))
    except (ValueError, InvalidSignature, UnsupportedAlgorithm):
        return False
    return True


def issued_by(cert_der: bytes, ca_pem: bytes) -> bool:
    """Whether the CA certificate ``ca_pem`` issued (signed) the certificate ``cert_der``."""
    try:
        cert = x509.load_der_x509_certificate(cert_der)
        cert.verify_directly_issued_by(x509.load_pem_x509_certificate(ca_pem))
    except (ValueError, TypeError, InvalidSignature, UnsupportedAlgorithm):
        return False
    return True
