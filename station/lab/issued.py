"""The register of issued certificates in ``<recordings>/certificates/`` (``station.certificate.issue``
writes it): read an issued certificate with its hashes checked, list them per transducer.  Light:
no rendering imported (the daemon's web side lists and serves from here)."""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from station.errors import StationError

FOLDER = "certificates"


class CertificateError(StationError):
    """A certificate that cannot be drafted, issued or read as asked (the message says why)."""


class CertificateNotFoundError(CertificateError):
    """No issued certificate with that number (404)."""


@dataclass(frozen=True)
class Issued:
    """An issued certificate as stored: its record (``<number>.json``) and where its files are."""

    number: str
    record: dict[str, Any]
    folder: Path

    def path(self, ext: str) -> Path:
        return self.folder / f"{self.number}.{ext}"


def canonical_hash(content: Any) -> str:
    return hashlib.sha256(json.dumps(content, sort_keys=True, separators=(",", ":"),
                                     ensure_ascii=False).encode()).hexdigest()


def read_issued(folder: Path, number: str) -> Issued:
    """An issued certificate, its hashes checked (CertificateError when unknown or altered)."""
    if not re.fullmatch(r"[A-Za-z0-9\-]{1,40}", number):
        raise CertificateError(f"not a certificate number: {number[:40]!r}")
    try:
        record = json.loads((folder / f"{number}.json").read_bytes())
    except FileNotFoundError:
        raise CertificateNotFoundError(f"no issued certificate {number}") from None
    it = Issued(number, record, folder)
    sha = record.get("sha256") or {}
    checks = {"content": canonical_hash(record.get("content")),
              **{ext: hashlib.sha256(it.path(ext).read_bytes()).hexdigest() for ext in ("html", "pdf", "xml")
                 if it.path(ext).exists()}}
    bad = [k for k, v in checks.items() if sha.get(k) != v]
    if bad:
        raise CertificateError(f"certificate {number} has been altered ({', '.join(bad)} does not match its hash)")
    return it


def list_issued(folder: Path, transducer_id: str | None = None) -> list[dict[str, Any]]:
    """The issued certificates (oldest first), optionally of one transducer: number, run, issue date,
    approver, what each replaces and whether it has been replaced (withdrawn)."""
    out: list[dict[str, Any]] = []
    if not folder.is_dir():
        return out
    for p in sorted(folder.glob("*.json")):
        rec = json.loads(p.read_bytes())
        if transducer_id is not None and rec.get("transducer_id") != transducer_id:
            continue
        marker = folder / f"{rec['number']}.replaced"
        replaced = json.loads(marker.read_bytes())["replaced_by"] if marker.exists() else None
        out.append({k: rec.get(k) for k in ("number", "transducer_id", "run_id", "recording", "issued_at",
                                            "approved_by", "replaces")} | {"replaced_by": replaced})
    return out


MEDIA = {"html": "text/html; charset=utf-8", "pdf": "application/pdf", "xml": "application/xml"}


def issued_file(folder: Path, number: str, ext: str) -> bytes:
    """The stored bytes of an issued certificate as issued (hashes checked)."""
    it = read_issued(folder, number)
    if not it.path(ext).exists():
        raise CertificateNotFoundError(f"certificate {number} has no .{ext} form")
    return it.path(ext).read_bytes()
