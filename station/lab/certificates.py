"""The issuing rules and the register of issued certificates, kept in the database and the audit
chain (never in files a user of the recordings folder can write).

* **Numbers** come from a sequence in the database (table ``certificate_numbers``): ``<prefix>-<year>-
  <NNNN>`` with the configured prefix (``certificate.number_prefix``: one per station, or one lab
  database shared by the stations, ``service.database``).  A number once taken is never given
  again, whatever happens to the files; a number whose issue failed stays taken (the refusal entry
  names it).
* **Rules** (:func:`check_issue`): the preparer is an enabled user of the lab (by default the run's
  operator), the approver is the authenticated user with the right to approve and is neither the
  preparer nor the operator; one live certificate per run, a second only replacing it with a
  reason.  A refused issue writes one ``certificate.refused`` entry and nothing else.
* **The register** (:func:`issued`) is read from the chain: ``certificate.issued`` entries (number,
  who prepared and approved, the SHA-256 of each file) and ``certificate.withdrawn`` ones.
"""

from __future__ import annotations

import json
import sqlite3
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from station.lab import audit, users
from station.lab.issued import FOLDER, CertificateError, CertificateNotFoundError
from station.service.store import Store

FILE_EXTS = ("html", "pdf", "xml", "json", "sig")



def file_key(number: str, ext: str) -> str:
    """A certificate file's path in the recordings folder (the chain's key)."""
    return f"{FOLDER}/{number}.{ext}"


def take_number(store: Store, prefix: str, year: int, run_id: str, folder: Path) -> str:
    """The next number of the sequence, taken for good (never given again)."""
    with store.transaction() as db:
        row = db.execute("SELECT max(seq) FROM certificate_numbers WHERE prefix = ? AND year = ?",
                         (prefix, year)).fetchone()
        seq = int(row[0] or 0) + 1
        while True:  # a number whose files exist (a database restored from an older backup) is skipped
            number = f"{prefix}-{year}-{seq:04d}"
            if not any((folder / f"{number}.{ext}").exists() for ext in FILE_EXTS):
                break
            seq += 1
        db.execute("INSERT INTO certificate_numbers (number, prefix, year, seq, run_id, taken, folder) "
                   "VALUES (?, ?, ?, ?, ?, ?, ?)", (number, prefix, year, seq, run_id, time.time(), str(folder)))
    return number


def _entries(db: sqlite3.Connection, actions: Iterable[str]) -> list[dict[str, Any]]:
    acts = list(actions)
    marks = ", ".join("?" for _ in acts)
    cur = db.execute(f"SELECT id, at, who, action, target, details, files FROM audit WHERE action IN ({marks}) "
                     "ORDER BY id", acts)
    return [{"id": r[0], "at": r[1], "who": r[2], "action": r[3], "target": r[4], "details": json.loads(r[5]),
             "files": json.loads(r[6])} for r in cur.fetchall()]


def issued(store: Store, transducer_id: str | None = None) -> list[dict[str, Any]]:
    """The issued certificates as the chain records them (oldest first): number, transducer, run,
    recording, issued_at, prepared_by, approved_by, replaces, replaced_by, withdrawn (the reason)."""
    with store.reading() as db:
        rows = _entries(db, (audit.CERTIFICATE_ISSUED, audit.CERTIFICATE_WITHDRAWN))
    out: dict[str, dict[str, Any]] = {}
    for e in rows:
        d = e["details"]
        if e["action"] == audit.CERTIFICATE_ISSUED:
            out[d["number"]] = {"number": d["number"], "transducer_id": d.get("transducer_id", ""),
                                "run_id": e["target"], "recording": d.get("recording", ""),
                                "issued_at": d.get("issued_at", ""), "prepared_by": d.get("prepared_by", ""),
                                "approved_by": e["who"], "replaces": d.get("replaces"), "replaced_by": None,
                                "withdrawn": None, "files": e["files"]}
            old = out.get(d.get("replaces") or "")
            if old is not None:
                old["replaced_by"] = d["number"]
                old["withdrawn"] = old["withdrawn"] or f"replaced by {d['number']}: {d.get('reason', '')}"
        elif d.get("number") in out:
            out[d["number"]]["withdrawn"] = f"withdrawn by {e['who']}: {d.get('reason', '')}"
    return [c for c in out.values() if transducer_id is None or c["transducer_id"] == transducer_id]


def one(store: Store, number: str) -> dict[str, Any]:
    """An issued certificate's record in the chain (CertificateNotFoundError if it has none)."""
    got = [c for c in issued(store) if c["number"] == number]
    if not got:
        raise CertificateNotFoundError(f"no issued certificate {number} in the audit trail")
    return got[0]


def live_of_run(store: Store, run_id: str) -> dict[str, Any] | None:
    """The run's certificate in force (issued, neither replaced nor withdrawn), if any."""
    live = [c for c in issued(store) if c["run_id"] == run_id and c["withdrawn"] is None]
    return live[-1] if live else None


def check_issue(store: Store, *, run_id: str, operator: str, approver: users.User, prepared_by: str | None,
                replaces: str | None, reason: str) -> str:
    """The issuing rules (module docstring); returns the preparer.  CertificateError (or
    ForbiddenError) with the reason; the caller records the refusal."""
    if not approver.may(users.Permission.APPROVE):
        raise users.ForbiddenError(f"user {approver.name} ({approver.role}) may not approve certificates; "
                                   "an approver does")
    prepared = prepared_by or operator
    if not prepared:
        raise CertificateError("the run has no recorded operator: name the lab user who prepared the certificate "
                               "(prepared_by)")
    who = users.get_user(store, prepared)
    if who is None or who.disabled:
        raise CertificateError(f"prepared_by {prepared[:40]!r} is not an enabled user of the lab; the preparer is "
                               "a user (the run's operator by default), never free text")
    if approver.name in (prepared, operator):
        raise users.ForbiddenError(f"{approver.name} {'prepared' if approver.name == prepared else 'ran'} this "
                                   "calibration: a second person approves it")
    live = live_of_run(store, run_id)
    if replaces is None:
        if live is not None:
            raise CertificateError(f"run {run_id} has a certificate in force ({live['number']}): a second one only "
                                   "replaces it (replaces, reason)")
    else:
        if not reason.strip():
            raise CertificateError("a replacing certificate says why (reason)")
        old = one(store, replaces)
        if old["withdrawn"] is not None:
            raise CertificateError(f"{replaces} is no longer in force ({old['withdrawn']})")
        if old["run_id"] != run_id and live is not None:
            raise CertificateError(f"run {run_id} has a certificate in force ({live['number']}); {replaces} is "
                                   "another run's")
    return prepared


def record_refusal(store: Store, who: str, run_id: str, why: str, number: str | None = None) -> int:
    """The one entry a refused issue writes."""
    return audit.append(store, who, audit.CERTIFICATE_REFUSED, run_id,
                        {"reason": why, **({"number": number} if number else {})})


def record_issue(store: Store, approver: str, run_id: str, record: dict[str, Any], hashes: dict[str, str],
                 head: tuple[int, str]) -> int:
    """The issue entry: the number, who prepared and approved, what it replaces, the chain's head
    before it and the SHA-256 of every file of the certificate."""
    details = {k: record.get(k) for k in ("number", "transducer_id", "recording", "issued_at", "prepared_by",
                                          "replaces", "reason")}
    details |= {"content_sha256": record["sha256"]["content"], "chain_head": {"id": head[0], "hash": head[1]}}
    return audit.append(store, approver, audit.CERTIFICATE_ISSUED, run_id, details,
                        files={file_key(record["number"], ext): sha for ext, sha in hashes.items()})


def withdraw(store: Store, who: users.User, number: str, reason: str) -> dict[str, Any]:
    """Withdraw a certificate in force (an approver; the reason in the audit trail)."""
    if not who.may(users.Permission.APPROVE):
        raise users.ForbiddenError(f"user {who.name} ({who.role}) may not withdraw certificates; an approver does")
    if not reason.strip():
        raise CertificateError("a withdrawal says why (reason)")
    c = one(store, number)
    if c["withdrawn"] is not None:
        raise CertificateError(f"{number} is no longer in force ({c['withdrawn']})")
    audit.append(store, who.name, audit.CERTIFICATE_WITHDRAWN, c["run_id"], {"number": number, "reason": reason})
    return one(store, number)
