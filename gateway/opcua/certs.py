"""The server's application instance certificate: generated, self-signed, when the configured files are
absent; and the client certificates of ``trusted_clients``.

The certificate carries what OPC UA Part 6 §6.2.2 asks of an application instance certificate: the
application URI and the host's name in subjectAltName, key usage for signing and key encipherment,
and both TLS extended key usages; RSA 2048 with SHA-256 (Basic256Sha256).
"""

from __future__ import annotations

import datetime
import hashlib
import logging
import os
import socket
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

__all__ = ["application_uri", "ensure_certificate", "thumbprint", "trusted_thumbprints"]

log = logging.getLogger("gateway.opcua")


def application_uri(host: str | None = None) -> str:
    """The server's application URI: ``urn:<host>:slc-gateway`` (the certificate carries it)."""
    return f"urn:{host or socket.gethostname()}:slc-gateway"


def thumbprint(der: bytes) -> str:
    """A certificate's thumbprint as OPC UA gives it: the SHA-1 of its DER, hex."""
    return hashlib.sha1(der).hexdigest()  # the thumbprint OPC UA defines


def ensure_certificate(certificate: Path, private_key: Path, uri: str) -> bool:
    """Generate a self-signed certificate and its key at the two paths when either is absent; True if it did."""
    if certificate.is_file() and private_key.is_file():
        return False
    host = socket.gethostname()
    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"slc-gateway@{host}"),
                      x509.NameAttribute(NameOID.ORGANIZATION_NAME, "slc-gateway")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(days=1)).not_valid_after(now + datetime.timedelta(days=3650))
        .add_extension(x509.SubjectAlternativeName([x509.UniformResourceIdentifier(uri), x509.DNSName(host),
                                                    x509.DNSName("localhost")]), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=True, key_encipherment=True,
                                     data_encipherment=True, key_agreement=False, key_cert_sign=True,
                                     crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                       critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    certificate.parent.mkdir(parents=True, exist_ok=True)
    private_key.parent.mkdir(parents=True, exist_ok=True)
    pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                            serialization.NoEncryption())
    descriptor = os.open(private_key, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "wb") as out:
        out.write(pem)
    certificate.write_bytes(cert.public_bytes(serialization.Encoding.DER))
    log.info("opcua: generated a self-signed certificate %s (thumbprint %s) and its key %s", certificate,
             thumbprint(certificate.read_bytes()), private_key)
    return True


def trusted_thumbprints(directory: Path) -> set[str]:
    """The thumbprints of the certificates (DER or PEM) in ``directory`` (none: it does not exist)."""
    found: set[str] = set()
    if not directory.is_dir():
        return found
    for path in sorted(directory.iterdir()):
        if not path.is_file():
            continue
        data = path.read_bytes()
        try:
            cert = x509.load_pem_x509_certificate(data) if data.lstrip().startswith(b"-----") else (
                x509.load_der_x509_certificate(data))
        except ValueError:
            log.warning("opcua: %s in trusted_clients is not a certificate: ignored", path)
            continue
        found.add(thumbprint(cert.public_bytes(serialization.Encoding.DER)))
    return found
