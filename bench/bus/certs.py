"""A certificate authority per deployment and one certificate per bench identity (mutual TLS).

`bench certs DEPLOYMENT` writes, into the deployment's certificate directory:

    ca.pem              the deployment's CA certificate (every host needs it)
    ca.key              the CA's private key (mode 0600; keep it off the bench hosts)
    <identity>.pem      one certificate per identity, CN = the identity (node name, launcher, router)
    <identity>.key      its private key (mode 0600; only the host that runs the identity needs it)
    secoc.key           the deployment's CAN SecOC key, 32 hex digits (mode 0600; the launcher's
                        host needs it: it hands it to the CAN nodes in each run's scenario.json;
                        every host of a deployment derives the data topics' key from it,
                        bench/bus/data_auth.py)

The common name is what Zenoh's access control matches (`cert_common_names`), so the CN of a
certificate *is* the node's identity on the bus: whoever holds `controller.key` may command.
Keys are ECDSA P-256 (rustls, under Zenoh's TLS link, accepts them; RSA-2048 keys take ~10x longer
to generate). Each certificate carries both serverAuth and clientAuth usages because a bench peer
is both: it listens for some links and connects others.
"""
from __future__ import annotations

import datetime as dt
import ipaddress
import os
import stat
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from bench.bus.private_files import PrivateKeyError, read_private_key

CA_NAME = "ca"
DEFAULT_VALIDITY_DAYS = 365
PRIVATE_KEY_MODE = 0o600
SECOC_KEY_NAME = "secoc.key"


class CertificateError(ValueError):
    """A certificate or key that cannot be used (missing, expired, readable by others, wrong CA)."""


@dataclass(frozen=True)
class Identity:
    """The files one bench identity presents on its TLS links."""

    name: str
    ca_path: Path
    cert_path: Path
    key_path: Path


def identity_files(cert_dir: Path, name: str) -> Identity:
    cert_dir = Path(cert_dir)
    return Identity(name, cert_dir / f"{CA_NAME}.pem", cert_dir / f"{name}.pem", cert_dir / f"{name}.key")


def _write_private_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    """Create the key file with mode 0600 from the start (never world-readable, not even briefly)."""
    data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())
    if path.exists():
        path.unlink()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, PRIVATE_KEY_MODE)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def write_secoc_key(cert_dir: Path) -> Path:
    """A new random AES-128 key for the deployment's CAN bus (SecOC), mode 0600 from the start."""
    import secrets
    path = Path(cert_dir) / SECOC_KEY_NAME
    Path(cert_dir).mkdir(parents=True, exist_ok=True)
    if path.exists():
        path.unlink()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, PRIVATE_KEY_MODE)
    with os.fdopen(fd, "w") as f:
        f.write(secrets.token_hex(16) + "\n")
    return path


def read_secoc_key(cert_dir: Path) -> str | None:
    """The deployment's SecOC key (hex), None if it has none; refused if others can read it."""
    path = Path(cert_dir) / SECOC_KEY_NAME
    if not path.is_file():
        return None
    try:
        return read_private_key(path, 16, f"SecOC key {str(path)!r}", "AES-128").hex()
    except PrivateKeyError as exc:
        raise CertificateError(str(exc)) from None


def _name(common_name: str, deployment: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, f"orbit-hil-bench {deployment}"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def make_ca(cert_dir: Path, deployment: str, days: int = DEFAULT_VALIDITY_DAYS) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """A fresh self-signed CA in cert_dir (ca.pem, ca.key)."""
    cert_dir = Path(cert_dir)
    cert_dir.mkdir(parents=True, exist_ok=True)
    key = ec.generate_private_key(ec.SECP256R1())
    now = dt.datetime.now(dt.timezone.utc)
    name = _name(f"{deployment} bench CA", deployment)
    cert = (
        x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                     data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                     crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    (cert_dir / f"{CA_NAME}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    _write_private_key(cert_dir / f"{CA_NAME}.key", key)
    return cert, key


def load_ca(cert_dir: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    cert_dir = Path(cert_dir)
    cert = x509.load_pem_x509_certificate((cert_dir / f"{CA_NAME}.pem").read_bytes())
    key = serialization.load_pem_private_key((cert_dir / f"{CA_NAME}.key").read_bytes(), password=None)
    return cert, key


def issue(cert_dir: Path, name: str, ca: tuple[x509.Certificate, ec.EllipticCurvePrivateKey],
          addresses: tuple[str, ...] = (), days: int = DEFAULT_VALIDITY_DAYS,
          not_before: dt.datetime | None = None) -> Identity:
    """Certificate `<name>.pem` (CN = name) signed by `ca`, and its key `<name>.key` (0600).

    addresses: IP addresses or host names the identity listens on, as subject alternative names
    (the bench turns name verification off, see session.py, but tools such as openssl s_client
    want them). not_before lets a test make an expired certificate.
    """
    ca_cert, ca_key = ca
    files = identity_files(cert_dir, name)
    key = ec.generate_private_key(ec.SECP256R1())
    start = not_before or dt.datetime.now(dt.timezone.utc) - dt.timedelta(minutes=5)
    alt_names: list[x509.GeneralName] = [x509.DNSName(name)]
    for address in addresses:
        try:
            alt_names.append(x509.IPAddress(ipaddress.ip_address(address)))
        except ValueError:
            alt_names.append(x509.DNSName(address))
    cert = (
        x509.CertificateBuilder().subject_name(x509.Name([*ca_cert.subject.get_attributes_for_oid(NameOID.ORGANIZATION_NAME),
                                                     x509.NameAttribute(NameOID.COMMON_NAME, name)]))
        .issuer_name(ca_cert.subject).public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start).not_valid_after(start + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                     data_encipherment=False, key_agreement=False, key_cert_sign=False,
                                     crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                       critical=False)
        .add_extension(x509.SubjectAlternativeName(alt_names), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    files.cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    _write_private_key(files.key_path, key)
    if not files.ca_path.exists():
        files.ca_path.write_bytes(ca_cert.public_bytes(serialization.Encoding.PEM))
    return files


def write_deployment_certs(cert_dir: Path, deployment: str, identities: dict[str, tuple[str, ...]],
                           days: int = DEFAULT_VALIDITY_DAYS) -> dict[str, Identity]:
    """A new CA and one certificate per identity (name -> addresses it listens on)."""
    ca = make_ca(cert_dir, deployment, days)
    write_secoc_key(cert_dir)
    return {name: issue(cert_dir, name, ca, addresses, days) for name, addresses in identities.items()}


def check_identity(identity: Identity, now: dt.datetime | None = None) -> None:
    """Refuse, in one line, files that cannot work or must not be used.

    Checked before a session opens, so the user reads this line instead of a TLS handshake
    failure deep in Zenoh's log: missing files, a private key that group or others can read
    (ssh's rule), a certificate outside its validity period, a certificate whose CN is not the
    identity, a certificate not signed by the deployment's CA.
    """
    for what, path in (("CA certificate", identity.ca_path), ("certificate", identity.cert_path),
                       ("private key", identity.key_path)):
        if not path.is_file():
            raise CertificateError(f"{identity.name}: {what} {str(path)!r} is missing (run `bench certs`)")
    mode = stat.S_IMODE(identity.key_path.stat().st_mode)
    if mode & 0o077:
        raise CertificateError(f"{identity.name}: private key {str(identity.key_path)!r} is readable by others "
                               f"(mode {mode:04o}); chmod 600 it")
    try:
        cert = x509.load_pem_x509_certificate(identity.cert_path.read_bytes())
        ca = x509.load_pem_x509_certificate(identity.ca_path.read_bytes())
    except ValueError as exc:
        raise CertificateError(f"{identity.name}: {exc}") from exc
    now = now or dt.datetime.now(dt.timezone.utc)
    if now > cert.not_valid_after_utc:
        raise CertificateError(f"{identity.name}: certificate {str(identity.cert_path)!r} expired on "
                               f"{cert.not_valid_after_utc:%Y-%m-%d %H:%M} UTC; run `bench certs` again")
    if now < cert.not_valid_before_utc:
        raise CertificateError(f"{identity.name}: certificate {str(identity.cert_path)!r} is not valid before "
                               f"{cert.not_valid_before_utc:%Y-%m-%d %H:%M} UTC (check the host's clock)")
    common_names = [a.value for a in cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)]
    if common_names != [identity.name]:
        raise CertificateError(f"{identity.name}: certificate {str(identity.cert_path)!r} has CN {common_names}, "
                               f"not {identity.name!r}")
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature) as exc:
        raise CertificateError(f"{identity.name}: certificate {str(identity.cert_path)!r} is not signed by the "
                               f"deployment's CA {str(identity.ca_path)!r}") from exc
