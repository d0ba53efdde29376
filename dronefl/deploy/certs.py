"""Certificates and keys of a secure deployment (``dronefl deploy certs DIR``).

One CA signs everything; each file is named by who holds it::

    ca.crt, ca.key             the CA (ca.key stays with the operator)
    superlink.crt/.key         the SuperLink's TLS identity (HTTPS)
    zenoh-<role>.crt/.key      each process's Zenoh TLS identity (mutual TLS), role in
                               world, cloud, launcher, drone-<id>: its common name, by
                               which the others' access control knows it
    supernode-<id>, .pub       each drone's SuperNode key pair (OpenSSH, NIST P-384): the
                               SuperLink admits only SuperNodes whose public key is registered

Server certificates name the hosts in ``hosts`` (IP addresses or DNS names) as subject
alternative names; the default (127.0.0.1, localhost) is for one machine.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from dronefl.deploy.link import LinkTls, roles
from dronefl.io import atomic_write_bytes

DEFAULT_HOSTS = ("127.0.0.1", "localhost")
VALID_DAYS = 365


@dataclass(frozen=True)
class CertificateFolder:
    """Where the files of :func:`make_certificates` are (``folder`` as written)."""

    folder: Path

    @property
    def ca(self) -> Path:
        return self.folder / "ca.crt"

    @property
    def superlink(self) -> tuple[Path, Path]:
        """SuperLink certificate and key."""
        return self.folder / "superlink.crt", self.folder / "superlink.key"

    def zenoh(self, role: str) -> LinkTls:
        """The Zenoh TLS identity of ``role`` (``world``, ``cloud``, ``launcher``,
        ``drone-<id>``)."""
        return LinkTls(
            self.ca, self.folder / f"zenoh-{role}.crt", self.folder / f"zenoh-{role}.key", role
        )

    def supernode_key(self, drone_id: int) -> Path:
        return self.folder / f"supernode-{drone_id}"

    def supernode_public_key(self, drone_id: int) -> Path:
        return self.folder / f"supernode-{drone_id}.pub"

    def check(self, paths: Sequence[Path]) -> None:
        """Raise ``FileNotFoundError`` naming the first of ``paths`` that is missing."""
        for path in paths:
            if not path.is_file():
                raise FileNotFoundError(f"{path}: certificate or key file missing")


def make_certificates(
    folder: Path, drone_ids: Sequence[int], hosts: Sequence[str] = DEFAULT_HOSTS
) -> CertificateFolder:
    """Write a CA, the SuperLink's and every process's certificates, and one SuperNode key
    pair per drone into ``folder``; ``ValueError`` if ``folder`` (or the nearest of its
    parents that exists) is a file."""
    folder = Path(folder)
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        where = "" if existing == folder else f"{folder}: "
        raise ValueError(f"{where}{existing} is a file, not a folder")
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "DroneFL deployment CA")])
    now = dt.datetime.now(dt.UTC)
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=VALID_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                key_cert_sign=True,
                crl_sign=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .sign(ca_key, hashes.SHA256())
    )
    out = CertificateFolder(folder)
    _write_key(folder / "ca.key", ca_key)
    atomic_write_bytes(out.ca, ca.public_bytes(serialization.Encoding.PEM))
    leaves = [("superlink", *out.superlink)] + [
        (role, out.zenoh(role).certificate, out.zenoh(role).key) for role in roles(drone_ids)
    ]
    for name, cert_path, key_path in leaves:
        key = ec.generate_private_key(ec.SECP256R1())
        _write_key(key_path, key)
        cert = _leaf(name, key, ca, ca_key, hosts, now)
        atomic_write_bytes(cert_path, cert.public_bytes(serialization.Encoding.PEM))
    for drone_id in drone_ids:
        key = ec.generate_private_key(ec.SECP384R1())
        private = key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.OpenSSH,
            serialization.NoEncryption(),
        )
        public = key.public_key().public_bytes(
            serialization.Encoding.OpenSSH, serialization.PublicFormat.OpenSSH
        )
        atomic_write_bytes(out.supernode_key(drone_id), private)
        atomic_write_bytes(out.supernode_public_key(drone_id), public + b"\n")
        out.supernode_key(drone_id).chmod(0o600)
    return out


def _leaf(
    name: str,
    key: ec.EllipticCurvePrivateKey,
    ca: x509.Certificate,
    ca_key: ec.EllipticCurvePrivateKey,
    hosts: Sequence[str],
    now: dt.datetime,
) -> x509.Certificate:
    """A certificate whose common name is ``name``, valid as TLS server and client for every
    host in ``hosts``."""
    names: list[x509.GeneralName] = []
    for host in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
        .issuer_name(ca.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=VALID_DAYS))
        .add_extension(x509.SubjectAlternativeName(names), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .sign(ca_key, hashes.SHA256())
    )


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    pem = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    atomic_write_bytes(path, pem)
    path.chmod(0o600)
