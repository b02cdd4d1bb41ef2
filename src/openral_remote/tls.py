"""TLS files checked before a session opens: each fault is one line naming its file.

Zenoh reads the files only when a link is made, and a bad one then shows up as a handshake that
fails (or a listener that never starts) with a message about neither the file nor the fix. Here
every file is read once, bounded, and checked for what breaks a link: missing or unreadable, not
PEM, outside its validity dates, a certificate that does not belong to its key or was not signed
by the authority given, a key Zenoh cannot read (encrypted).

A certificate file may carry intermediates after the certificate itself; the certificate must be
signed by the CA, or by an intermediate of the file that is itself signed by the CA (directly or
through others of the file). Some certificate of the file being signed by the CA, or being it,
is not enough: the peer checks the first one.
"""

from __future__ import annotations

import datetime as dt

from openral_core import ROSConfigError, ROSDependencyMissing
from openral_core.config_files import expand_user_path, read_config_file
from openral_remote.config import TlsConfig

try:
    from cryptography import x509
    from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.types import PrivateKeyTypes
    from cryptography.x509.oid import NameOID
except ImportError as exc:
    raise ROSDependencyMissing("cryptography", extra="remote", needed_for="checking TLS files") from exc

__all__ = ["check_tls"]

_MAX_PEM_BYTES = 1 << 20
"""A CA bundle is tens of kilobytes; anything past this is not one."""

_MISSING = "check the path; a relative one is taken from the working directory"
_PUBLIC = (serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)


def check_tls(tls: TlsConfig, *, prefix: str = "zenoh.tls.", now: dt.datetime | None = None) -> None:
    """Refuse TLS files a link would fail on.

    Args:
        tls: The files.
        prefix: Put before ``ca``, ``cert`` and ``key`` to name the field (``--tls-`` for options).
        now: The time validity is judged at (default: now, UTC).

    Raises:
        ROSConfigError: Naming the field and the file: what is wrong with it and what to do.
    """
    when = now or dt.datetime.now(dt.UTC)
    ca_field = f"{prefix}ca"
    authorities = _certificates(tls.ca, ca_field, "CA certificate")
    for authority in authorities:
        _current(authority, tls.ca, ca_field, when)
    if tls.cert is None or tls.key is None:
        return
    cert_field, key_field = f"{prefix}cert", f"{prefix}key"
    chain = _certificates(tls.cert, cert_field, "certificate")
    _current(chain[0], tls.cert, cert_field, when)
    key = _private_key(tls.key, key_field)
    if key.public_key().public_bytes(*_PUBLIC) != chain[0].public_key().public_bytes(*_PUBLIC):
        raise ROSConfigError(
            f"certificate {_shown(tls.cert)} does not belong to the key {_shown(tls.key)}",
            field=cert_field,
            hint="give the key the certificate was made for",
        )
    if not _chains_to(chain[0], chain[1:], authorities):
        raise ROSConfigError(
            f"certificate {_shown(tls.cert)} ({_subject(chain[0])}) is not signed by the CA in {_shown(tls.ca)} "
            f"({', '.join(_subject(a) for a in authorities)})",
            field=cert_field,
            hint="sign it with that CA, or name the CA that signed it",
        )


def _certificates(path: str, field: str, what: str) -> list[x509.Certificate]:
    text = read_config_file(path, field=field, max_bytes=_MAX_PEM_BYTES, missing_hint=_MISSING)
    try:
        found = x509.load_pem_x509_certificates(text.encode("utf-8"))
    except ValueError:
        found = []
    if not found:
        raise ROSConfigError(
            f"{_shown(path)} holds no PEM certificate",
            field=field,
            hint=f"name the {what}: a PEM file with -----BEGIN CERTIFICATE-----",
        )
    return found


def _current(certificate: x509.Certificate, path: str, field: str, now: dt.datetime) -> None:
    start, end = certificate.not_valid_before_utc, certificate.not_valid_after_utc
    if now < start:
        raise ROSConfigError(
            f"certificate {_shown(path)} ({_subject(certificate)}) is not valid before {start:%Y-%m-%d %H:%M} UTC",
            field=field,
            hint="check this machine's clock, or issue a certificate valid now",
        )
    if now > end:
        raise ROSConfigError(
            f"certificate {_shown(path)} ({_subject(certificate)}) expired on {end:%Y-%m-%d %H:%M} UTC",
            field=field,
            hint="issue a new one",
        )


def _private_key(path: str, field: str) -> PrivateKeyTypes:
    text = read_config_file(path, field=field, max_bytes=_MAX_PEM_BYTES, missing_hint=_MISSING)
    try:
        return serialization.load_pem_private_key(text.encode("utf-8"), password=None)
    except TypeError:  # cryptography's word for a key that needs a password
        raise ROSConfigError(
            f"private key {_shown(path)} is encrypted",
            field=field,
            hint="Zenoh reads keys without a passphrase: write it unencrypted (openssl pkey -in K -out K2)",
        ) from None
    except (ValueError, UnsupportedAlgorithm):
        raise ROSConfigError(
            f"{_shown(path)} holds no PEM private key",
            field=field,
            hint="name the key: a PEM file with -----BEGIN PRIVATE KEY-----",
        ) from None


def _chains_to(
    certificate: x509.Certificate, intermediates: list[x509.Certificate], authorities: list[x509.Certificate]
) -> bool:
    """Whether ``certificate`` is signed by one of ``authorities``, or by intermediates that lead to one."""
    trusted = list(authorities)
    pending = [candidate for candidate in intermediates if _is_authority(candidate)]
    while True:
        if any(_issued_by(certificate, authority) for authority in trusted):
            return True
        reached = [candidate for candidate in pending if any(_issued_by(candidate, a) for a in trusted)]
        if not reached:
            return False
        trusted += reached
        pending = [candidate for candidate in pending if candidate not in reached]


def _is_authority(certificate: x509.Certificate) -> bool:
    """Whether ``certificate`` may sign others (basic constraints say it is a CA)."""
    try:
        return bool(certificate.extensions.get_extension_for_class(x509.BasicConstraints).value.ca)
    except x509.ExtensionNotFound:
        return False


def _issued_by(certificate: x509.Certificate, authority: x509.Certificate) -> bool:
    if certificate == authority:
        return True
    try:
        certificate.verify_directly_issued_by(authority)
    except (ValueError, TypeError, InvalidSignature):
        return False
    return True


def _subject(certificate: x509.Certificate) -> str:
    names = certificate.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return f"CN={names[0].value!s}" if names else certificate.subject.rfc4514_string() or "no subject"


def _shown(path: str) -> str:
    return str(expand_user_path(path))
