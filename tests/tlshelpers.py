"""Certificates for the TLS tests, made here with the cryptography package: a private CA, a
server certificate for 127.0.0.1 and localhost, and client certificates for mutual TLS."""

from __future__ import annotations

import datetime
import ipaddress
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID


@dataclass(frozen=True)
class Pki:
    ca: str  # CA certificate (PEM)
    server_cert: str
    server_key: str
    client_cert: str  # signed by the CA
    client_key: str
    stranger_cert: str  # self-signed: not the CA's
    stranger_key: str


def _write_key(key, path: Path) -> str:
    path.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    return str(path)


def _cert(
    subject: str, key, issuer_name, issuer_key, *, ca: bool, usage, sans=()
) -> x509.Certificate:
    now = datetime.datetime.now(datetime.UTC)
    builder = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)]))
        .issuer_name(issuer_name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True)
    )
    if usage:
        builder = builder.add_extension(x509.ExtendedKeyUsage(usage), critical=False)
    if sans:
        builder = builder.add_extension(x509.SubjectAlternativeName(list(sans)), critical=False)
    return builder.sign(issuer_key, hashes.SHA256())


def make_pki(directory: Path) -> Pki:
    directory = Path(directory)
    pem = serialization.Encoding.PEM
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "renderfarm test CA")])
    ca = _cert("renderfarm test CA", ca_key, ca_name, ca_key, ca=True, usage=None)
    (directory / "ca.pem").write_bytes(ca.public_bytes(pem))
    server_key = ec.generate_private_key(ec.SECP256R1())
    sans = [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
    server = _cert("renderfarm server", server_key, ca_name, ca_key, ca=False,
                   usage=[ExtendedKeyUsageOID.SERVER_AUTH], sans=sans)  # fmt: skip
    (directory / "server.pem").write_bytes(server.public_bytes(pem))
    client_key = ec.generate_private_key(ec.SECP256R1())
    client = _cert("renderfarm worker", client_key, ca_name, ca_key, ca=False,
                   usage=[ExtendedKeyUsageOID.CLIENT_AUTH])  # fmt: skip
    (directory / "client.pem").write_bytes(client.public_bytes(pem))
    stranger_key = ec.generate_private_key(ec.SECP256R1())
    stranger_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "stranger")])
    stranger = _cert("stranger", stranger_key, stranger_name, stranger_key, ca=False,
                     usage=[ExtendedKeyUsageOID.CLIENT_AUTH])  # fmt: skip
    (directory / "stranger.pem").write_bytes(stranger.public_bytes(pem))
    return Pki(
        ca=str(directory / "ca.pem"),
        server_cert=str(directory / "server.pem"),
        server_key=_write_key(server_key, directory / "server-key.pem"),
        client_cert=str(directory / "client.pem"),
        client_key=_write_key(client_key, directory / "client-key.pem"),
        stranger_cert=str(directory / "stranger.pem"),
        stranger_key=_write_key(stranger_key, directory / "stranger-key.pem"),
    )
