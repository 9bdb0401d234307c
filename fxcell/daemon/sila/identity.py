"""The SiLA server's identity, kept with the daemon's state: its UUID, certificate and key.

Generated at the first start with ``--sila`` and stored beside the daemon's token file
(``daemon.sila.state_dir`` to put them elsewhere), owner-only like the token:

- ``sila-server-uuid``: the SiLA Server UUID, stable across restarts (schedulers know the
  cell by it; discovery announces it);
- ``sila-cert.pem`` and ``sila-key.pem``: a self-signed certificate (common name ``SiLA2``,
  the server UUID in the SiLA extension ``1.3.6.1.4.1.58583``, valid for the daemon's address,
  ``localhost`` and the host name), as SiLA 2 expects from servers without a trusted one.
  Clients pin it (its PEM goes out with discovery); ``fxcell info`` shows its SHA-256
  fingerprint for checking it by eye. A certificate that does not cover the address the
  daemon now listens on is replaced (with a warning: clients must pin the new one).
"""

from __future__ import annotations

import datetime
import hashlib
import ipaddress
import logging
import os
import socket
import stat
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fxcell.config import CellConfig
from fxcell.errors import ConfigError

log = logging.getLogger(__name__)

UUID_FILE = "sila-server-uuid"
CERT_FILE = "sila-cert.pem"
KEY_FILE = "sila-key.pem"
SILA_UUID_OID = "1.3.6.1.4.1.58583"
"""The certificate extension in which SiLA 2 servers carry their UUID."""
VALID_DAYS = 3650


def state_dir(config: CellConfig) -> Path:
    """Where the identity is kept: ``daemon.sila.state_dir``, else beside the token file."""
    configured = config.daemon.sila.state_dir
    if configured is not None:
        return Path(configured).expanduser()
    return Path(config.daemon.token_file).expanduser().parent


@dataclass(frozen=True, slots=True)
class Identity:
    """The server's UUID and TLS credentials (PEM)."""

    server_uuid: uuid.UUID
    certificate: bytes
    private_key: bytes

    @property
    def fingerprint(self) -> str:
        return fingerprint(self.certificate)


def fingerprint(certificate: bytes) -> str:
    """The SHA-256 fingerprint of a PEM certificate, as browsers and openssl show it."""
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding

    der = x509.load_pem_x509_certificate(certificate).public_bytes(Encoding.DER)
    digest = hashlib.sha256(der).hexdigest().upper()
    return ":".join(digest[i : i + 2] for i in range(0, len(digest), 2))


def read_certificate(config: CellConfig) -> bytes | None:
    """The stored certificate (PEM), or ``None`` before the first start with ``--sila``."""
    try:
        return (state_dir(config) / CERT_FILE).read_bytes()
    except OSError:
        return None


def load_or_create(config: CellConfig) -> Identity:
    """The server's identity; created (owner-only files) where missing."""
    directory = state_dir(config)
    try:
        directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"daemon.sila: cannot create {directory}: {exc.strerror}") from None
    server_uuid = _load_or_create_uuid(directory / UUID_FILE)
    host = config.daemon.host
    cert_path, key_path = directory / CERT_FILE, directory / KEY_FILE
    if cert_path.exists() and key_path.exists():
        _check_private(key_path)
        certificate, key = cert_path.read_bytes(), key_path.read_bytes()
        if _covers(certificate, host, server_uuid):
            return Identity(server_uuid, certificate, key)
        log.warning(
            "SiLA certificate %s does not cover %s (or another server UUID): generating a new "
            "one; clients that pinned the old one must pin the new one",
            cert_path,
            host,
        )
    key, certificate = _generate(server_uuid, host)
    _write_private(key_path, key)
    _write_private(cert_path, certificate)
    log.info("SiLA certificate generated: %s (SHA-256 %s)", cert_path, fingerprint(certificate))
    return Identity(server_uuid, certificate, key)


def _load_or_create_uuid(path: Path) -> uuid.UUID:
    try:
        text = path.read_text().strip()
    except FileNotFoundError:
        value = uuid.uuid4()
        _write_private(path, f"{value}\n".encode())
        return value
    except OSError as exc:
        raise ConfigError(f"daemon.sila: cannot read {path}: {exc.strerror}") from None
    try:
        return uuid.UUID(text)
    except ValueError:
        raise ConfigError(f"daemon.sila: {path} holds no UUID; delete it to make one") from None


def _check_private(path: Path) -> None:
    mode = path.stat().st_mode
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ConfigError(
            f"daemon.sila: {path} is accessible by other users "
            f"(mode {stat.S_IMODE(mode):o}); run: chmod 600 {path}"
        )


def _write_private(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "wb") as out:
            out.write(data)
        os.replace(tmp, path)
    except OSError as exc:
        raise ConfigError(f"daemon.sila: cannot write {path}: {exc.strerror}") from None


def _names(host: str) -> tuple[list[str], list[str]]:
    """IP addresses and DNS names a certificate for ``host`` covers."""
    ips = {"127.0.0.1"}
    names = {"localhost", socket.gethostname()}
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        names.add(host)
    else:
        if not address.is_unspecified:
            ips.add(str(address))
    return sorted(ips), sorted(names)


def _covers(certificate: bytes, host: str, server_uuid: uuid.UUID) -> bool:
    from cryptography import x509

    try:
        cert = x509.load_pem_x509_certificate(certificate)
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        carried = cert.extensions.get_extension_for_oid(x509.ObjectIdentifier(SILA_UUID_OID))
    except (ValueError, x509.ExtensionNotFound):
        return False
    value = carried.value
    if cert.subject != _subject(server_uuid):
        return False
    if not isinstance(value, x509.UnrecognizedExtension) or value.value != str(server_uuid).encode(
        "ascii"
    ):
        return False
    if cert.not_valid_after_utc < datetime.datetime.now(datetime.UTC) + datetime.timedelta(days=1):
        return False
    ips, names = _names(host)
    have_ips = {str(ip) for ip in san.get_values_for_type(x509.IPAddress)}
    have_names = set(san.get_values_for_type(x509.DNSName))
    return set(ips) <= have_ips and set(names) <= have_names


def _subject(server_uuid: uuid.UUID) -> Any:
    """Common name ``SiLA2`` (what SiLA clients expect of a self-signed server certificate);
    the server UUID as organisational unit, so that a client pinning several cells' certificates
    tells them apart (they would otherwise share one subject, which TLS looks issuers up by)."""
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    return x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "fxcell"),
            x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, str(server_uuid)),
            x509.NameAttribute(NameOID.COMMON_NAME, "SiLA2"),
        ]
    )


def _generate(server_uuid: uuid.UUID, host: str) -> tuple[bytes, bytes]:
    """A private key and a self-signed certificate for ``host`` (PEM)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = _subject(server_uuid)
    ips, names = _names(host)
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(hours=1))
        .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                key_encipherment=False,
                key_cert_sign=True,
                crl_sign=False,
                key_agreement=True,
                encipher_only=False,
                decipher_only=False,
                content_commitment=False,
                data_encipherment=False,
            ),
            critical=True,
        )
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
        .add_extension(
            x509.SubjectAlternativeName(
                [x509.IPAddress(ipaddress.ip_address(ip)) for ip in ips]
                + [x509.DNSName(n) for n in names]
            ),
            critical=False,
        )
        .add_extension(
            x509.UnrecognizedExtension(
                x509.ObjectIdentifier(SILA_UUID_OID), str(server_uuid).encode("ascii")
            ),
            critical=False,
        )
        .sign(key, hashes.SHA256())
    )
    key_pem = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    return key_pem, cert.public_bytes(serialization.Encoding.PEM)
