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
from station.certificate.dcc import build_dcc
from station.certificate.dcc import validate as validate_dcc
from station.certificate.render import certificate_html
from station.config import CertificateConfig
from station.lab.issued import (
    FOLDER,
    CertificateError,
    Issued,
    canonical_hash,
    issued_file,
    list_issued,
    read_issued,
)
from station.recording import read_recording
from station.report.render import html_to_pdf

APPROVING_ROLES = ("approver", "admin")


class UserRoles(Protocol):
    def role_of(self, name: str) -> str | None:
        """The person's role ('technician' | 'approver' | 'admin') or None when unknown."""


@dataclass(frozen=True)
class ConfigRoles:
    """UserRoles from a configuration's ``certificate.users``."""

    config: CertificateConfig

    def role_of(self, name: str) -> str | None:
        return next((u.role for u in self.config.users if u.name == name), None)


def _config(recording: Path) -> CertificateConfig:
    cfg = read_recording(recording).config
    section = cfg.get("certificate") if isinstance(cfg, dict) else None
    return CertificateConfig.model_validate(section or {})


def folder_of(recording: Path) -> Path:
    return Path(recording).resolve().parent / FOLDER


@dataclass(frozen=True)
class MappingRoles:
    """UserRoles from a mapping name -> role (the daemon passes the authenticated approver's)."""

    roles: dict[str, str]

    def role_of(self, name: str) -> str | None:
        return self.roles.get(name)


def draft(recording: Path, prepared_by: str = "", register: dict[str, Any] | None = None) -> tuple[dict[str, Any], str]:
    """(content, HTML) of the draft certificate of a recording's stored identification."""
    content = certificate_content(recording, Approval(prepared_by=prepared_by), register)
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
          roles: UserRoles | None = None, now: datetime | None = None,
          register: dict[str, Any] | None = None, number: str | None = None,
          signature: dict[str, str] | None = None) -> Issued:
    """Issue the certificate of a recording's stored identification (module docstring); refused with
    a CertificateError when the approver may not approve, approves their own work, a reference
    standard was overdue at the calibration, the result was not stored, or ``replaces`` is unknown,
    of another transducer or already replaced.  ``number``: taken from the lab's sequence by the
    daemon (``station.lab.certificates``); None numbers it in this folder (a folder of its own).
    ``signature``: the lab key's fingerprint and the detached signature file the daemon writes
    (``station.lab.signing``), printed on the certificate and named in the DCC."""
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
    content = certificate_content(recording, Approval(prepared_by=prepared_by), register)
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
        number = number or _next_number(folder, cc.number_prefix, now.year)
        approval = Approval("issued", number, prepared_by, approver, str(role), now.isoformat(timespec="seconds"),
                            replaces, reason)
        content = {**content, "approval": {**content["approval"], **approval.__dict__,
                                           **({"signature": signature} if signature else {})}}
        html = certificate_html(content).encode()
        xml = build_dcc(content)
        if cc.dcc_schema:
            validate_dcc(xml, cc.dcc_schema)  # refused before anything is written
        pdf = html_to_pdf(html.decode())
        record = {"number": number, "transducer_id": content["item"]["transducer_id"],
                  "run_id": content["run"]["run_id"], "recording": recording.name,
                  "issued_at": approval.issued_at, "prepared_by": prepared_by, "approved_by": approver,
                  "replaces": replaces, "reason": reason, "content": content,
                  "sha256": {"content": canonical_hash(content), "html": hashlib.sha256(html).hexdigest(),
                             "pdf": hashlib.sha256(pdf).hexdigest(), "xml": hashlib.sha256(xml).hexdigest()}}
        _write_once(folder / f"{number}.html", html)
        _write_once(folder / f"{number}.pdf", pdf)
        _write_once(folder / f"{number}.xml", xml)
        _write_once(folder / f"{number}.json", json.dumps(record, indent=1, ensure_ascii=False).encode())
        if replaces:
            _write_once(folder / f"{replaces}.replaced", json.dumps({"replaced_by": number, "reason": reason}).encode())
    return Issued(number, record, folder)


def run_document(recording: Path, ext: str, register: dict[str, Any] | None = None, *,
                 draft_only: bool = False) -> bytes:
    """A run's certificate: the latest issued one of its run that has not been replaced, else its
    draft rendered now (HTML, PDF or a DCC marked as a draft).  ``draft_only``: the draft whatever the
    folder holds (the daemon knows from its audit trail that none is in force)."""
    recording = Path(recording)
    folder = folder_of(recording)
    mine = [] if draft_only else [c for c in list_issued(folder)
                                  if c["recording"] == recording.name and c["replaced_by"] is None]
    if mine:
        return issued_file(folder, str(mine[-1]["number"]), ext)
    if ext == "xml":  # the DCC is built from the content alone: no page (nor its Bode plot) drawn for it
        return build_dcc(certificate_content(recording, Approval(), register))
    _, html = draft(recording, register=register)
    return html.encode() if ext == "html" else html_to_pdf(html)
