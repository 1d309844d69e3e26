"""Drafts, approval and the register of issued certificates.

A stored identification of a recording is a *draft* certificate (rendered on demand, never stored,
marked DRAFT).  A second person whose role is ``approver`` or ``admin`` *issues* it: it gets the next
number (``<prefix>-<year>-<NNNN>``, sequential per certificates folder under a file lock) and its
content, HTML and PDF are written once, atomically, to ``<recordings>/certificates/<number>.*`` with
the SHA-256 of each in ``<number>.json``; nothing there is ever rewritten.  A correction is a new
certificate naming the one it replaces (``replaces``, ``reason``); the replaced one stays as issued
and a ``<old>.replaced`` marker (written once) lists it as withdrawn.

Users and roles come from the configuration the recording holds (``certificate.users``) through
``UserRoles``; the laboratory's user register plugs in through the same protocol.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import re
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

from station.certificate.content import Approval, certificate_content
from station.certificate.render import certificate_html, html_to_pdf
from station.config import CertificateConfig
from station.errors import StationError
from station.recording import read_recording

APPROVING_ROLES = ("approver", "admin")
FOLDER = "certificates"


class CertificateError(StationError):
    """A certificate that cannot be drafted, issued or read as asked (the message says why)."""


class UserRoles(Protocol):
    def role_of(self, name: str) -> str | None:
        """The person's role ('technician' | 'approver' | 'admin') or None when unknown."""


@dataclass(frozen=True)
class ConfigRoles:
    """UserRoles from a configuration's ``certificate.users``."""

    config: CertificateConfig

    def role_of(self, name: str) -> str | None:
        return next((u.role for u in self.config.users if u.name == name), None)


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


def _config(recording: Path) -> CertificateConfig:
    cfg = read_recording(recording).config
    section = cfg.get("certificate") if isinstance(cfg, dict) else None
    return CertificateConfig.model_validate(section or {})


def folder_of(recording: Path) -> Path:
    return Path(recording).resolve().parent / FOLDER


def draft(recording: Path, prepared_by: str = "") -> tuple[dict[str, Any], str]:
    """(content, HTML) of the draft certificate of a recording's stored identification."""
    content = certificate_content(recording, Approval(prepared_by=prepared_by))
    return content, certificate_html(content)


@contextmanager
def _locked(folder: Path) -> Iterator[None]:
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / ".lock", "a+b") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _write_once(path: Path, data: bytes) -> None:
    """Write a new file atomically (tmp, fsync, link: refuses to replace an existing one)."""
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise CertificateError(f"{path.name} exists already: an issued certificate is never rewritten") from None
    finally:
        tmp.unlink(missing_ok=True)
    dfd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)


def _next_number(folder: Path, prefix: str, year: int) -> str:
    pat = re.compile(rf"^{re.escape(prefix)}-{year}-(\d{{4,}})\.json$")
    seq = [int(m.group(1)) for p in folder.iterdir() if (m := pat.match(p.name))]
    return f"{prefix}-{year}-{max(seq, default=0) + 1:04d}"


def issue(recording: Path, *, prepared_by: str, approver: str, replaces: str | None = None, reason: str = "",
          roles: UserRoles | None = None, now: datetime | None = None) -> Issued:
    """Issue the certificate of a recording's stored identification (module docstring); refused with
    a CertificateError when the approver may not approve, approves their own work, a reference
    standard was overdue at the calibration, the result was not stored, or ``replaces`` is unknown,
    of another transducer or already replaced."""
    recording = Path(recording)
    cc = _config(recording)
    roles = roles or ConfigRoles(cc)
    if roles.role_of(prepared_by) is None:
        raise CertificateError(f"{prepared_by!r} is not a known user (certificate.users)")
    role = roles.role_of(approver)
    if role not in APPROVING_ROLES:
        raise CertificateError(f"{approver!r} may not approve certificates (role {role or 'unknown'}; "
                               f"needs one of {', '.join(APPROVING_ROLES)})")
    if approver == prepared_by:
        raise CertificateError("a certificate is approved by a second person, not by the one who prepared it")
    if replaces and not reason:
        raise CertificateError("a replacing certificate says why (reason)")
    now = now or datetime.now(UTC)
    content = certificate_content(recording, Approval(prepared_by=prepared_by))
    if "not stored" in content["method"]["result"]:
        raise CertificateError("no identification is stored with this recording: identify it first")
    day = content["run"]["start_time"][:10]
    overdue = [s["id"] for s in content["standards"] if s["due_date"] < day]
    if overdue:
        raise CertificateError(f"reference standard(s) {', '.join(overdue)} were overdue for calibration on {day}")
    folder = folder_of(recording)
    with _locked(folder):
        if replaces:
            old = read_issued(folder, replaces)
            if old.record["transducer_id"] != content["item"]["transducer_id"]:
                raise CertificateError(f"{replaces} is the certificate of another transducer")
            if (folder / f"{replaces}.replaced").exists():
                raise CertificateError(f"{replaces} has been replaced already")
        number = _next_number(folder, cc.number_prefix, now.year)
        approval = Approval("issued", number, prepared_by, approver, str(role), now.isoformat(timespec="seconds"),
                            replaces, reason)
        content = {**content, "approval": {**content["approval"], **approval.__dict__}}
        html = certificate_html(content).encode()
        pdf = html_to_pdf(html.decode())
        record = {"number": number, "transducer_id": content["item"]["transducer_id"],
                  "run_id": content["run"]["run_id"], "recording": recording.name,
                  "issued_at": approval.issued_at, "prepared_by": prepared_by, "approved_by": approver,
                  "replaces": replaces, "reason": reason, "content": content,
                  "sha256": {"content": canonical_hash(content), "html": hashlib.sha256(html).hexdigest(),
                             "pdf": hashlib.sha256(pdf).hexdigest()}}
        _write_once(folder / f"{number}.html", html)
        _write_once(folder / f"{number}.pdf", pdf)
        _write_once(folder / f"{number}.json", json.dumps(record, indent=1, ensure_ascii=False).encode())
        if replaces:
            _write_once(folder / f"{replaces}.replaced", json.dumps({"replaced_by": number, "reason": reason}).encode())
    return Issued(number, record, folder)


def read_issued(folder: Path, number: str) -> Issued:
    """An issued certificate, its hashes checked (CertificateError when unknown or altered)."""
    if not re.fullmatch(r"[A-Za-z0-9\-]{1,40}", number):
        raise CertificateError(f"not a certificate number: {number[:40]!r}")
    try:
        record = json.loads((folder / f"{number}.json").read_bytes())
    except FileNotFoundError:
        raise CertificateError(f"no issued certificate {number}") from None
    it = Issued(number, record, folder)
    sha = record.get("sha256") or {}
    checks = {"content": canonical_hash(record.get("content")),
              **{ext: hashlib.sha256(it.path(ext).read_bytes()).hexdigest() for ext in ("html", "pdf")
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
