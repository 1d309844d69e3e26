"""The lab's signing key: Ed25519 (``cryptography``), one private key file readable by the daemon's
user only, its public key published (``GET /signing-key``) and its fingerprint printed on each
certificate.

What is signed is a *statement* of an issued certificate (:func:`statement`): its number, the
SHA-256 of its content and of each of its files (HTML, PDF, DCC XML), the audit chain's head at the
issue and the key's fingerprint, as canonical JSON.  The signed statement is stored beside the
certificate as ``<number>.sig`` (JSON: the statement, the signature, the public key); the DCC names
that file.  :func:`verify_file` is what a customer runs (``station verify CERTIFICATE``): with the
public key alone, off-line, it checks the signature and that the file in hand is one of the signed
ones, byte for byte.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import stat
import time
from pathlib import Path
from typing import Any

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from station.lab.issued import CertificateError

ALGORITHM = "Ed25519"
SIG_FORMAT = "sinecal-certificate-signature/1"


class SigningError(CertificateError):
    """No usable signing key, or a signature that does not verify (the message says which; 409)."""


def fingerprint(public: Ed25519PublicKey) -> str:
    """SHA-256 of the raw 32-byte public key, hex in groups of four (what the certificate prints)."""
    raw = public.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    h = hashlib.sha256(raw).hexdigest()
    return ":".join(h[i:i + 4] for i in range(0, len(h), 4))


def public_pem(public: Ed25519PublicKey) -> str:
    return public.public_bytes(serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo).decode()


def init_key(path: Path, *, rotate: bool = False) -> tuple[Ed25519PrivateKey, Path | None]:
    """Write a new private key (mode 0600, never over an existing one).  ``rotate``: the existing key
    is kept as ``<name>.retired-<UTC time>`` (0600) and its public key beside it (``.pub``), so that
    certificates signed with it still verify.  Returns (the key, the retired file or None)."""
    retired = None
    if path.exists():
        if not rotate:
            raise SigningError(f"{path} exists: the lab's key is never overwritten (station keys rotate retires it)")
        old = load_key(path)
        retired = path.with_name(f"{path.name}.retired-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}")
        os.link(path, retired)
        retired.with_suffix(retired.suffix + ".pub").write_text(public_pem(old.public_key()))
    key = Ed25519PrivateKey.generate()
    pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                            serialization.NoEncryption())
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.new")
    tmp.unlink(missing_ok=True)
    write_new(tmp, pem, 0o600)
    os.replace(tmp, path)
    return key, retired


def write_new(path: Path, data: bytes, mode: int) -> None:
    """Write a file that must not exist yet (FileExistsError otherwise), with ``mode`` from its
    creation on, and sync it."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)


def load_key(path: Path) -> Ed25519PrivateKey:
    """The lab's private key; refused when missing, not Ed25519, or readable by others than its owner."""
    try:
        st = path.stat()
    except FileNotFoundError:
        raise SigningError(f"no signing key at {path}: station keys init creates it") from None
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise SigningError(f"{path} is readable by others (mode {stat.S_IMODE(st.st_mode):o}); chmod 600 it")
    key = serialization.load_pem_private_key(path.read_bytes(), password=None)
    if not isinstance(key, Ed25519PrivateKey):
        raise SigningError(f"{path} is not an Ed25519 key")
    return key


def load_public(pem: bytes) -> Ed25519PublicKey:
    key = serialization.load_pem_public_key(pem)
    if not isinstance(key, Ed25519PublicKey):
        raise SigningError("the public key is not an Ed25519 key")
    return key


def _canonical(doc: dict[str, Any]) -> bytes:
    return json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode()


def statement(number: str, content_sha256: str, files: dict[str, str], head: tuple[int, str],
              key_fingerprint: str) -> dict[str, Any]:
    """What the lab signs for an issued certificate (module docstring); ``files``: name -> SHA-256."""
    return {"format": SIG_FORMAT, "number": number, "content_sha256": content_sha256, "files": dict(files),
            "audit_chain_head": {"id": head[0], "hash": head[1]}, "key_fingerprint": key_fingerprint,
            "algorithm": ALGORITHM}


def sign(key: Ed25519PrivateKey, doc: dict[str, Any]) -> bytes:
    """The signature file's bytes: the statement, its signature and the public key."""
    sig = key.sign(_canonical(doc))
    return json.dumps({"statement": doc, "signature": base64.b64encode(sig).decode(),
                       "public_key": public_pem(key.public_key())}, indent=1, ensure_ascii=False).encode()


def verify_file(certificate: Path, public: Ed25519PublicKey, signature: Path | None = None) -> dict[str, Any]:
    """Check a certificate file (HTML, PDF or DCC XML) against the lab's public key alone: the
    signature file (``<number>.sig`` beside it unless given) verifies with this key, and the file's
    SHA-256 is one of those signed (whatever the file is called now).  Returns the statement;
    SigningError naming what fails."""
    sig_path = signature or certificate.with_suffix(".sig")
    try:
        doc = json.loads(sig_path.read_bytes())
        st, sig = doc["statement"], base64.b64decode(doc["signature"], validate=True)
    except FileNotFoundError:
        raise SigningError(f"no signature file {sig_path.name} beside {certificate.name}") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise SigningError(f"{sig_path.name} is not a signature file ({exc})") from None
    try:
        public.verify(sig, _canonical(st))
    except InvalidSignature:
        raise SigningError(f"{sig_path.name}: the signature does not verify with the key {fingerprint(public)} "
                           "(the signature file was changed, or another key signed it)") from None
    if st.get("key_fingerprint") != fingerprint(public):
        raise SigningError(f"{sig_path.name} names the key {st.get('key_fingerprint')}, not this one")
    actual = hashlib.sha256(certificate.read_bytes()).hexdigest()
    files = st.get("files", {})
    if actual not in files.values():  # by content, whatever the file is called now
        raise SigningError(f"{certificate.name} is not a file the lab signed for {st.get('number')} (its SHA-256 "
                           f"{actual[:16]}... is none of {', '.join(sorted(files))})")
    return dict(st)
