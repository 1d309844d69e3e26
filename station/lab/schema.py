"""The lab's tables and the upgrade of an older station's database to them (schema 3).

The upgrade only adds: columns of ``runs`` (who started a run, the transducer record and the
reference standards it used, the SHA-256 of its recording) and new tables.  The audit trail is
append-only in the database itself: triggers refuse any UPDATE or DELETE of it.
"""

from __future__ import annotations

import sqlite3

from station.lab import chain

RUN_COLUMNS = {  # columns added to runs, with their definitions
    "operator": "TEXT NOT NULL DEFAULT ''",
    "transducer_json": "TEXT NOT NULL DEFAULT '{}'",
    "standards_json": "TEXT NOT NULL DEFAULT '[]'",
    "recording_sha256": "TEXT",
}

STATEMENTS = (
    """CREATE TABLE IF NOT EXISTS transducers (
        id TEXT PRIMARY KEY,
        type TEXT NOT NULL DEFAULT '',
        serial TEXT NOT NULL DEFAULT '',
        capacity_N REAL NOT NULL,
        sensitivity_V_per_N REAL NOT NULL,
        end_mass_kg REAL,
        end_mass_std_kg REAL,
        owner TEXT NOT NULL DEFAULT '',
        updated REAL NOT NULL,
        updated_by TEXT NOT NULL)""",
    """CREATE TABLE IF NOT EXISTS standards (
        id TEXT PRIMARY KEY,
        kind TEXT NOT NULL,
        description TEXT NOT NULL DEFAULT '',
        certificate_id TEXT NOT NULL,
        issuer TEXT NOT NULL,
        due_date TEXT NOT NULL,
        uncertainty REAL NOT NULL,
        uncertainty_unit TEXT NOT NULL,
        in_use INTEGER NOT NULL DEFAULT 1,
        updated REAL NOT NULL,
        updated_by TEXT NOT NULL)""",
    """CREATE TABLE IF NOT EXISTS station_state (
        key TEXT PRIMARY KEY,
        value TEXT NOT NULL,
        updated REAL NOT NULL,
        updated_by TEXT NOT NULL)""",
    """CREATE TABLE IF NOT EXISTS users (
        name TEXT PRIMARY KEY,
        role TEXT NOT NULL,
        password TEXT NOT NULL DEFAULT '',
        created REAL NOT NULL,
        created_by TEXT NOT NULL,
        disabled INTEGER NOT NULL DEFAULT 0)""",
    """CREATE TABLE IF NOT EXISTS tokens (
        hash TEXT PRIMARY KEY,
        user TEXT NOT NULL REFERENCES users(name),
        label TEXT NOT NULL DEFAULT '',
        created REAL NOT NULL,
        revoked REAL)""",
    """CREATE TABLE IF NOT EXISTS sessions (
        hash TEXT PRIMARY KEY,
        user TEXT NOT NULL REFERENCES users(name),
        created REAL NOT NULL,
        expires REAL NOT NULL,
        ended REAL)""",
    """CREATE TABLE IF NOT EXISTS certificate_numbers (
        number TEXT PRIMARY KEY,
        prefix TEXT NOT NULL,
        year INTEGER NOT NULL,
        seq INTEGER NOT NULL,
        run_id TEXT NOT NULL,
        taken REAL NOT NULL,
        folder TEXT NOT NULL DEFAULT '',
        UNIQUE (prefix, year, seq))""",
    """CREATE TABLE IF NOT EXISTS audit (
        id INTEGER PRIMARY KEY AUTOINCREMENT,
        at REAL NOT NULL,
        who TEXT NOT NULL,
        action TEXT NOT NULL,
        target TEXT NOT NULL DEFAULT '',
        details TEXT NOT NULL DEFAULT '{}')""",
    """CREATE TABLE IF NOT EXISTS transducer_policy (
        transducer_id TEXT PRIMARY KEY,
        tolerances_json TEXT NOT NULL DEFAULT '{}',
        interval_days REAL,
        check_standard INTEGER NOT NULL DEFAULT 0,
        updated REAL NOT NULL,
        updated_by TEXT NOT NULL)""",
    """CREATE TABLE IF NOT EXISTS as_left (
        run_id TEXT NOT NULL,
        transducer_id TEXT NOT NULL,
        parameter TEXT NOT NULL,
        value REAL NOT NULL,
        unit TEXT NOT NULL,
        note TEXT NOT NULL DEFAULT '',
        at REAL NOT NULL,
        by TEXT NOT NULL,
        PRIMARY KEY (run_id, parameter))""",
    """CREATE TABLE IF NOT EXISTS login_locks (
        key TEXT PRIMARY KEY,
        failures INTEGER NOT NULL,
        locked_until REAL NOT NULL)""",
    "CREATE INDEX IF NOT EXISTS audit_target ON audit(target, id)",
    "CREATE INDEX IF NOT EXISTS runs_transducer ON runs(transducer_id, created)",
    """CREATE TRIGGER IF NOT EXISTS audit_no_update BEFORE UPDATE ON audit
        BEGIN SELECT RAISE(ABORT, 'the audit trail is append-only'); END""",
    """CREATE TRIGGER IF NOT EXISTS audit_no_delete BEFORE DELETE ON audit
        BEGIN SELECT RAISE(ABORT, 'the audit trail is append-only'); END""",
)


def upgrade(db: sqlite3.Connection) -> list[str]:
    """Bring a database (of any earlier schema, or new) to the lab's tables, inside the caller's
    transaction; returns the columns added to ``runs``."""
    have = {r[1] for r in db.execute("PRAGMA table_info(runs)").fetchall()}
    added = []
    for name, definition in RUN_COLUMNS.items():
        if name not in have:
            db.execute(f"ALTER TABLE runs ADD COLUMN {name} {definition}")
            added.append(name)
    for stmt in STATEMENTS:
        db.execute(stmt)
    chain.upgrade(db)  # the hash chain's columns; an older trail is chained as it stands
    return added
