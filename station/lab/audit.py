"""The audit trail: who did what, when, to what.  Append-only: this module only inserts and reads,
and the database refuses any UPDATE or DELETE of the table (triggers, ``schema.py``).  Each entry is
a link of a hash chain (``chain.py``): it holds the previous entry's hash, the SHA-256 of the files
it concerns and its own hash, so that a change made around the triggers is found too.

A state change writes its audit record in the same transaction as the change itself
(``with store.transaction() as db: ...; record(db, ...)``), so there is never one without the other.
"""

from __future__ import annotations

import json
import sqlite3
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from station.lab import chain
from station.lab.store import Store

SYSTEM = "system"  # the daemon itself (start-up seeding, identification); "" never appears

# what the trail records (the ``action`` column)
RUN_STARTED = "run.started"
RUN_ABORTED = "run.aborted"
RUN_ENDED = "run.ended"
RUN_IDENTIFIED = "run.identified"
RESULT_REIDENTIFIED = "result.reidentified"
RESULT_STORED = "result.stored"  # an analysis stored beside a recording (model gap, campaign)
ESTOP_RAISED = "estop.raised"
ESTOP_ACKNOWLEDGED = "estop.acknowledged"
CERTIFICATE_APPROVED = "certificate.approved"
REGISTER_CHANGED = "register.changed"
TRANSDUCER_MOUNTED = "register.mounted"
USER_CHANGED = "user.changed"
LOGIN = "user.login"
LOGIN_REFUSED = "user.login_refused"
LOGOUT = "user.logout"
TOKEN_ISSUED = "user.token_issued"
TOKEN_REVOKED = "user.token_revoked"
LOGIN_LOCKED = "user.login_locked"  # failed logins locked a name or a client address out for a while
DATABASE_UPGRADED = "database.upgraded"
RECORDING_RECOVERED = "run.recovered"  # a partial recording recovered at start-up, hashed into the chain
CERTIFICATE_ISSUED = "certificate.issued"
KEY_CREATED = "signing_key.created"  # the lab's signing key made (its fingerprint; never the key)
CERTIFICATE_REFUSED = "certificate.refused"
CERTIFICATE_WITHDRAWN = "certificate.withdrawn"
AUDIT_EXCEPTION = chain.EXCEPTION


@dataclass(frozen=True)
class AuditEntry:
    """One line of the trail: ``at`` UNIX seconds, ``who`` a user name (or ``system``, or ``anonymous``
    for an emergency stop without credentials), ``details`` a JSON object."""

    id: int
    at: float
    who: str
    action: str
    target: str
    details: dict[str, Any]
    files: dict[str, str | None]
    hash: str

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def record(db: sqlite3.Connection, who: str, action: str, target: str = "",
           details: dict[str, Any] | None = None, *, at: float | None = None,
           files: dict[str, str | None] | None = None) -> int:
    """Append one entry on ``db`` (a connection inside the caller's transaction, which holds the
    write lock: the chain's head cannot move meanwhile); returns its id.  ``files``: the SHA-256 of
    the files the entry concerns (paths in the recordings folder; None for one removed on purpose)."""
    if not who:
        raise ValueError("an audit entry names who did it")
    row: dict[str, Any] = {"at": float(time.time() if at is None else at), "who": who, "action": action,
                           "target": target, "details": json.dumps(details or {}, sort_keys=True, default=str),
                           "files": json.dumps(files or {}, sort_keys=True)}
    last = db.execute("SELECT seq FROM sqlite_sequence WHERE name = 'audit'").fetchone()
    head_id, row["prev"] = chain.head(db)
    row["id"] = max(int(last[0]) if last is not None else 0, head_id) + 1  # never an id used before
    row["hash"] = chain.entry_hash(row)
    db.execute("INSERT INTO audit (id, at, who, action, target, details, files, prev, hash) "
               "VALUES (:id, :at, :who, :action, :target, :details, :files, :prev, :hash)", row)
    return int(row["id"])


def append(store: Store, who: str, action: str, target: str = "", details: dict[str, Any] | None = None,
           *, files: dict[str, str | None] | None = None) -> int:
    """Append one entry in a transaction of its own (for changes that are not in the database)."""
    with store.transaction() as db:
        return record(db, who, action, target, details, files=files)


def seal_results(store: Store, who: str, action: str, target: str, recording: Path,
                 details: dict[str, Any] | None = None) -> int:
    """Append an entry vouching for a run's results files as they are now (``chain.seal``: each
    file's SHA-256, None for one the chain knew that is gone).  Called by whoever wrote them, while
    it still holds the recording's lock."""
    now = chain.results_hashes(recording)
    _, prefix = chain.run_files(target, recording.name)
    with store.transaction() as db:
        before = chain.expected_files(db, target, check=False)
        return record(db, who, action, target, details, files=chain.seal(before, now, prefix) or None)


def entries(store: Store, *, target: str | None = None, action: str | None = None, who: str | None = None,
            since: float | None = None, limit: int = 200, before_id: int | None = None) -> list[AuditEntry]:
    """The trail, newest first, filtered by target (a run id, a transducer id, ``user:<name>``, ...),
    action (exact, or a prefix ending in ``.``), who, time (UNIX s) and id (paging)."""
    where, args = [], list[Any]()
    if target is not None:
        where.append("target = ?")
        args.append(target)
    if action is not None:
        if action.endswith("."):
            where.append("substr(action, 1, ?) = ?")
            args.extend([len(action), action])
        else:
            where.append("action = ?")
            args.append(action)
    if who is not None:
        where.append("who = ?")
        args.append(who)
    if since is not None:
        where.append("at >= ?")
        args.append(since)
    if before_id is not None:
        where.append("id < ?")
        args.append(before_id)
    q = "SELECT * FROM audit" + (" WHERE " + " AND ".join(where) if where else "") + " ORDER BY id DESC LIMIT ?"
    args.append(int(limit))
    return [AuditEntry(r["id"], r["at"], r["who"], r["action"], r["target"], json.loads(r["details"]),
                       json.loads(r["files"]), r["hash"])
            for r in store.query(q, args)]
