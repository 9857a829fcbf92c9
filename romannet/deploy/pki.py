"""A small certificate authority for a fleet site: one CA, one certificate per identity (Python `cryptography`).

    site = generate_site(Path("/etc/romannet/pki"), actor_ids=["actor-0", "actor-1"],
                         router_hosts=["10.0.0.2", "router.lab"])

Zenoh's TLS links (rustls) authenticate both ends with these (mutual TLS): the router presents
`router.pem`, whose subject alternative names must hold every name or address clients dial; each client
presents its own certificate, whose common name (CN) is its identity in the router's access-control
policy (`cert_common_names`). Identities: `router`, `replay`, `learner`, `operator` and one per actor id.

Keys are ECDSA P-256 in PKCS#8 PEM, written with mode 0600 (certificates 0644). The CA key is kept beside
the certificates so a site can add an actor later (`generate_site` again with the same directory reuses
the CA and any identity that already has a certificate and key); move it offline where that matters.
Certificates are valid for `days` (default 825, the common upper bound for leaf certificates).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from romannet.common.keys import check_chunk

CA_NAME = "ca"
SERVICE_IDENTITIES = ("router", "replay", "learner", "operator")
ORGANIZATION = "RoManNet fleet"
_BACKDATE = dt.timedelta(minutes=5)  # tolerate small clock differences between machines


@dataclass(frozen=True)
class Identity:
    """Paths of one identity's certificate and private key (PEM)."""

    name: str
    cert: Path
    key: Path


@dataclass(frozen=True)
class Site:
    """Everything generate_site wrote (or found): the CA certificate and each identity."""

    directory: Path
    ca_cert: Path
    ca_key: Path
    identities: dict[str, Identity]

    def __getitem__(self, name: str) -> Identity:
        return self.identities[name]


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _write(path: Path, data: bytes, mode: int) -> None:
    """Write atomically with the given permissions (a key is never readable by others, even briefly)."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.chmod(tmp, mode)
    os.replace(tmp, path)


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, ORGANIZATION),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _alt_names(hosts: Iterable[str]) -> list[x509.GeneralName]:
    return [x509.IPAddress(ipaddress.ip_address(h)) if _is_ip(h) else x509.DNSName(h) for h in hosts]


def _is_ip(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


def _load_ca(cert_path: Path, key_path: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise ValueError(f"{key_path} is not an EC private key")
    return cert, key


def make_ca(directory: Path, days: int = 3650) -> tuple[Path, Path]:
    """Create (or reuse) the site CA in directory: (ca.pem, ca.key)."""
    cert_path, key_path = directory / f"{CA_NAME}.pem", directory / f"{CA_NAME}.key"
    if cert_path.is_file() and key_path.is_file():
        _load_ca(cert_path, key_path)  # fails loudly if they are not a usable pair of PEM files
        return cert_path, key_path
    key = _new_key()
    now = dt.datetime.now(dt.timezone.utc)
    name = _name(f"{ORGANIZATION} CA")
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - _BACKDATE).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, encipher_only=False,
                                         decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    directory.mkdir(parents=True, exist_ok=True)
    _write(key_path, _key_pem(key), 0o600)
    _write(cert_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return cert_path, key_path


def issue(directory: Path, name: str, hosts: Sequence[str] = (), days: int = 825) -> Identity:
    """Issue `<name>.pem` / `<name>.key` signed by the CA in directory, CN = name.

    hosts: DNS names and IP addresses this identity is reached at (its certificate's subject alternative
    names); a router needs every one its clients dial, a client none (its name is added anyway).
    """
    check_chunk("identity", name)
    ca_cert, ca_key = _load_ca(directory / f"{CA_NAME}.pem", directory / f"{CA_NAME}.key")
    key = _new_key()
    now = dt.datetime.now(dt.timezone.utc)
    alt = _alt_names(dict.fromkeys([*hosts, name]))  # ordered, without duplicates
    cert = (x509.CertificateBuilder().subject_name(_name(name)).issuer_name(ca_cert.subject)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - _BACKDATE).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=False, crl_sign=False,
                                         content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, encipher_only=False,
                                         decipher_only=False), critical=True)
            # Both uses: a router serves clients and dials other routers; a client could do either too.
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                  ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
            .add_extension(x509.SubjectAlternativeName(alt), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                           critical=False)
            .sign(ca_key, hashes.SHA256()))
    ident = Identity(name, directory / f"{name}.pem", directory / f"{name}.key")
    _write(ident.key, _key_pem(key), 0o600)
    _write(ident.cert, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return ident


def common_name(cert_path: Path) -> str:
    """The CN of a PEM certificate (what the router's access control matches)."""
    cert = x509.load_pem_x509_certificate(Path(cert_path).read_bytes())
    return str(cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value)


def _names_of(cert_path: Path) -> set[str]:
    """The DNS names and IP addresses (as text) in a certificate's subject alternative names."""
    cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return set()
    return {*san.get_values_for_type(x509.DNSName), *(str(ip) for ip in san.get_values_for_type(x509.IPAddress))}


def generate_site(directory: str | Path, actor_ids: Sequence[str], router_hosts: Sequence[str] = ("localhost",),
                  days: int = 825, force: bool = False) -> Site:
    """The CA plus a certificate for router, replay, learner, operator and each actor id, in directory.

    An identity that already has both files is kept unless force (then re-issued; the CA is always kept),
    except the router's when its certificate lacks one of router_hosts.
    """
    directory = Path(directory)
    if not actor_ids:
        raise ValueError("at least one actor id is needed")
    for actor_id in actor_ids:
        check_chunk("actor_id", actor_id)
        if actor_id in SERVICE_IDENTITIES:
            raise ValueError(f"actor id {actor_id!r} collides with a service identity")
    if len(set(actor_ids)) != len(actor_ids):
        raise ValueError(f"actor ids must be unique: {list(actor_ids)}")
    ca_cert, ca_key = make_ca(directory)
    identities: dict[str, Identity] = {}
    for name in (*SERVICE_IDENTITIES, *actor_ids):
        existing = Identity(name, directory / f"{name}.pem", directory / f"{name}.key")
        keep = not force and existing.cert.is_file() and existing.key.is_file()
        if keep and name == "router":
            keep = {str(ipaddress.ip_address(h)) if _is_ip(h) else h for h in router_hosts} <= _names_of(existing.cert)
        if keep:
            identities[name] = existing
        else:
            identities[name] = issue(directory, name, router_hosts if name == "router" else (), days)
    return Site(directory, ca_cert, ca_key, identities)
