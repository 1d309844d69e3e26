"""The audit trail: who did what, when, to what.  Append-only: this module only inserts and reads,
and the database refuses any UPDATE or DELETE of the table (triggers, ``schema.py``).

A state change writes its audit record in the same transaction as the change itself
(``with store.transaction() as db: ...; record(db, ...)``), so there is never one without the other.
"""

from __future__ import annotations

import json
import sqlite3
import time
from dataclasses import asdict, dataclass
from typing import Any

from station.service.store import Store

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
DATABASE_UPGRADED = "database.upgraded"


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

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def record(db: sqlite3.Connection, who: str, action: str, target: str = "",
           details: dict[str, Any] | None = None, *, at: float | None = None) -> int:
    """Append one entry on ``db`` (a connection inside the caller's transaction); returns its id."""
    if not who:
        raise ValueError("an audit entry names who did it")
    cur = db.execute("INSERT INTO audit (at, who, action, target, details) VALUES (?, ?, ?, ?, ?)",
                     (time.time() if at is None else at, who, action, target,
                      json.dumps(details or {}, sort_keys=True, default=str)))
    return int(cur.lastrowid or 0)


def append(store: Store, who: str, action: str, target: str = "", details: dict[str, Any] | None = None) -> int:
    """Append one entry in a transaction of its own (for changes that are not in the database)."""
    with store.transaction() as db:
        return record(db, who, action, target, details)


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
    return [AuditEntry(r["id"], r["at"], r["who"], r["action"], r["target"], json.loads(r["details"]))
            for r in store.query(q, args)]
