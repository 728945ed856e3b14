"""TLS for every TCP link: one fleet CA, one certificate per node, both sides authenticated.

A node's identity is its certificate's common name. ``ups certs ca DIR`` makes the fleet CA
(``DIR/ca.crt``, ``DIR/ca.key``); ``ups certs issue DIR NAME`` makes ``DIR/NAME.crt`` and
``DIR/NAME.key`` signed by it. Every daemon and node is then given ``--tls-ca``,
``--tls-cert`` and ``--tls-key``: it accepts only peers whose certificate the CA signed, and
shows its own. Host names are not checked: the CA's signature is what admits a peer, and the
name in it says who the peer is. A node also checks that its TCP-ECB is the fleet's broker:
its certificate must name the identity ``broker`` (``--tls-broker`` says another).
"""

from __future__ import annotations

import datetime
import os
import ssl
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ._errors import ConfigError

_CA_YEARS = 10
_CERT_YEARS = 2


@dataclass(frozen=True)
class Tls:
    """The files of one participant: the fleet CA's certificate, its own certificate and key."""

    ca: Path
    cert: Path
    key: Path
    broker: str = "broker"  #: the identity a node's TCP-ECB must show

    @classmethod
    def from_files(
        cls, ca: str | None, cert: str | None, key: str | None, broker: str = "broker"
    ) -> Tls | None:
        """All three, or none (plain TCP); anything else is a ``ConfigError``."""
        given = [x for x in (ca, cert, key) if x]
        if not given:
            return None
        if len(given) != 3:
            raise ConfigError("TLS needs all of --tls-ca, --tls-cert and --tls-key")
        assert ca and cert and key
        for path in (ca, cert, key):
            if not Path(path).is_file():
                raise ConfigError(f"no such file: {path}")
        return cls(Path(ca), Path(cert), Path(key), broker)

    def identity(self) -> str:
        """The common name of our own certificate: who we are to the others."""
        from cryptography import x509

        try:
            cert = x509.load_pem_x509_certificate(self.cert.read_bytes())
        except (OSError, ValueError) as exc:
            raise ConfigError(f"cannot read the certificate {self.cert}: {exc}") from exc
        names = cert.subject.get_attributes_for_oid(x509.oid.NameOID.COMMON_NAME)
        if not names:
            raise ConfigError(f"the certificate {self.cert} has no common name")
        return str(names[0].value)

    def server(self) -> ssl.SSLContext:
        """For a listening socket: clients must show a certificate the CA signed."""
        context = self._context(ssl.Purpose.CLIENT_AUTH)
        context.verify_mode = ssl.CERT_REQUIRED
        return context

    def client(self) -> ssl.SSLContext:
        """For a connection we make: the server must show a certificate the CA signed."""
        context = self._context(ssl.Purpose.SERVER_AUTH)
        context.check_hostname = False  # identities are names in the fleet, not host names
        context.verify_mode = ssl.CERT_REQUIRED
        return context

    def _context(self, purpose: ssl.Purpose) -> ssl.SSLContext:
        try:
            context = ssl.create_default_context(purpose, cafile=str(self.ca))
            context.load_cert_chain(str(self.cert), str(self.key))
        except (OSError, ssl.SSLError) as exc:
            raise ConfigError(f"cannot use the TLS files {self.cert}, {self.key}: {exc}") from exc
        context.minimum_version = ssl.TLSVersion.TLSv1_2
        return context


def identity(transport: Any) -> str | None:
    """The common name of the certificate the peer of ``transport`` showed (None: plain TCP)."""
    cert = transport.get_extra_info("peercert") if transport is not None else None
    if not cert:
        return None
    for rdn in cert.get("subject", ()):
        for key, value in rdn:
            if key == "commonName":
                return str(value)
    return None


# --- making certificates (``ups certs``) ----------------------------------------------------


def make_ca(directory: str | Path, name: str = "ups fleet CA") -> tuple[Path, Path]:
    """Make ``DIR/ca.crt`` and ``DIR/ca.key``; refuses to overwrite them."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec

    folder = Path(directory)
    crt, key_path = folder / "ca.crt", folder / "ca.key"
    _refuse_overwrite(crt, key_path)
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(x509.oid.NameOID.COMMON_NAME, name)])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=365 * _CA_YEARS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(ca=True), critical=True)
        .sign(key, hashes.SHA256())
    )
    _write(folder, crt, cert, key_path, key)
    return crt, key_path


def issue(directory: str | Path, name: str, hosts: Sequence[str] = ()) -> tuple[Path, Path]:
    """Make ``DIR/NAME.crt`` and ``DIR/NAME.key``, signed by ``DIR/ca.crt``; ``name`` becomes
    the certificate's common name: the identity of whoever holds it. ``hosts`` (DNS names or
    IP addresses) go into its subject alternative names, for clients that check the name of
    the host they connect to (a Zenoh router's certificate: ``tls/HOST:PORT``)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    if not name or "/" in name or name.startswith(".") or name == "ca":
        raise ConfigError(f"not a usable identity name: {name!r}")
    folder = Path(directory)
    try:
        ca_cert = x509.load_pem_x509_certificate((folder / "ca.crt").read_bytes())
        ca_key = serialization.load_pem_private_key((folder / "ca.key").read_bytes(), None)
    except (OSError, ValueError) as exc:
        raise ConfigError(
            f"no usable CA in {folder} (make one with 'ups certs ca'): {exc}"
        ) from exc
    if not isinstance(ca_key, ec.EllipticCurvePrivateKey):
        raise ConfigError(f"{folder / 'ca.key'} is not a key made by 'ups certs ca'")
    crt, key_path = folder / f"{name}.crt", folder / f"{name}.key"
    _refuse_overwrite(crt, key_path)
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.UTC)
    builder = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(x509.oid.NameOID.COMMON_NAME, name)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=365 * _CERT_YEARS))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(ca=False), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage(
                [x509.oid.ExtendedKeyUsageOID.SERVER_AUTH, x509.oid.ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
    )
    if hosts:
        builder = builder.add_extension(
            x509.SubjectAlternativeName([_general_name(host) for host in hosts]), critical=False
        )
    cert = builder.sign(ca_key, hashes.SHA256())
    _write(folder, crt, cert, key_path, key)
    return crt, key_path


def _general_name(host: str) -> Any:
    import ipaddress

    from cryptography import x509

    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        return x509.DNSName(host)


def _key_usage(*, ca: bool) -> Any:
    from cryptography import x509

    return x509.KeyUsage(
        digital_signature=True, content_commitment=False, key_encipherment=False,
        data_encipherment=False, key_agreement=not ca, key_cert_sign=ca, crl_sign=ca,
        encipher_only=False, decipher_only=False,
    )  # fmt: skip


def _refuse_overwrite(*paths: Path) -> None:
    for path in paths:
        if path.exists():
            raise ConfigError(f"{path} exists already; remove it first to make a new one")


def _write(folder: Path, crt: Path, cert: Any, key_path: Path, key: Any) -> None:
    from cryptography.hazmat.primitives import serialization

    folder.mkdir(parents=True, exist_ok=True)
    crt.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    pem = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as out:
        out.write(pem)
