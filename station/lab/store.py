"""Runs and identification jobs in SQLite (WAL): what survives a restart of the daemon.

Two connections, each behind its own lock: one for writes, one for reads (WAL lets the reads go on
while a writer, this process's or another's, holds the write lock).  The daemon calls them from
threads, never from its event loop (``station.service.db``).  Writes are autocommitted; WAL with
``synchronous=NORMAL`` keeps a committed state change through a kill of the process (a power cut
may lose the last few, never corrupt the file).
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Literal, get_args

from station.lab.schema import upgrade
from station.run.procedure import StepState

READ_BUSY_TIMEOUT_S = 2.0  # the read connection's wait for a lock (an exclusive one of another process)
SCHEMA_VERSION = 3  # 2: the emergency-stop latch (estops); 3: the lab (register, users, audit; station.lab.schema)

RunState = Literal["queued", "running", "identifying", "completed", "aborted", "failed", "interrupted"]
RUN_STATES: tuple[RunState, ...] = get_args(RunState)
ACTIVE_STATES = ("queued", "running")  # the run holds the rig
FINAL_STATES = ("completed", "aborted", "failed", "interrupted")
JOB_STATES = ("queued", "running", "done", "failed")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    id TEXT PRIMARY KEY,
    state TEXT NOT NULL,
    transducer_id TEXT NOT NULL,
    top_mass_kg REAL NOT NULL,
    request_json TEXT NOT NULL,
    plan_json TEXT NOT NULL,
    created REAL NOT NULL,
    started REAL,
    ended REAL,
    step INTEGER,
    n_steps INTEGER NOT NULL,
    step_state TEXT NOT NULL DEFAULT '',
    fraction REAL NOT NULL DEFAULT 0,
    samples INTEGER NOT NULL DEFAULT 0,
    lost_samples INTEGER NOT NULL DEFAULT 0,
    message TEXT NOT NULL DEFAULT '',
    reason TEXT NOT NULL DEFAULT '',
    recording TEXT,
    result_name TEXT,
    operator TEXT NOT NULL DEFAULT '',
    transducer_json TEXT NOT NULL DEFAULT '{}',
    standards_json TEXT NOT NULL DEFAULT '[]',
    recording_sha256 TEXT
);
CREATE INDEX IF NOT EXISTS runs_state ON runs(state);
CREATE INDEX IF NOT EXISTS runs_created ON runs(created);
CREATE TABLE IF NOT EXISTS jobs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    run_id TEXT NOT NULL REFERENCES runs(id),
    kind TEXT NOT NULL,
    state TEXT NOT NULL,
    attempts INTEGER NOT NULL DEFAULT 0,
    created REAL NOT NULL,
    started REAL,
    finished REAL,
    error TEXT NOT NULL DEFAULT ''
);
CREATE INDEX IF NOT EXISTS jobs_state ON jobs(state, id);
CREATE TABLE IF NOT EXISTS estops (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    raised REAL NOT NULL,
    source TEXT NOT NULL,
    detail TEXT NOT NULL DEFAULT '',
    acknowledged REAL,
    acknowledged_by TEXT,
    note TEXT NOT NULL DEFAULT ''
);
"""


@dataclass
class RunRow:
    """A run as stored.  Times are UNIX seconds; ``recording`` is the file name in the recordings
    folder (never a path outside it); ``fraction`` is the progress in [0, 1]."""

    id: str
    state: RunState
    transducer_id: str
    top_mass_kg: float
    request_json: str
    plan_json: str
    created: float
    n_steps: int
    started: float | None = None
    ended: float | None = None
    step: int | None = None
    step_state: StepState = ""
    fraction: float = 0.0
    samples: int = 0
    lost_samples: int = 0
    message: str = ""
    reason: str = ""
    recording: str | None = None
    result_name: str | None = None
    operator: str = ""  # the user who started the run ('' in databases from before the lab tables)
    transducer_json: str = "{}"  # the register's record of the transducer as the run used it
    standards_json: str = "[]"  # the reference standards the run used, as recorded then
    recording_sha256: str | None = None  # of the closed recording (station.lab.integrity)

    @property
    def request(self) -> dict[str, Any]:
        return json.loads(self.request_json)

    @property
    def plan(self) -> dict[str, Any]:
        return json.loads(self.plan_json)


@dataclass
class JobRow:
    id: int
    run_id: str
    kind: str
    state: str
    attempts: int
    created: float
    started: float | None
    finished: float | None
    error: str


@dataclass
class EStopRow:
    """One emergency stop: when (UNIX s) and from where it was raised, and who acknowledged it when."""

    id: int
    raised: float
    source: str
    detail: str
    acknowledged: float | None
    acknowledged_by: str | None
    note: str


_RUN_COLS = tuple(f.name for f in fields(RunRow))


def _split(script: str) -> list[str]:
    """A schema script as single statements (run one by one inside the upgrade's transaction)."""
    return [s.strip() for s in script.split(";") if s.strip()]
_JOB_COLS = tuple(f.name for f in fields(JobRow))


class Store:
    """The daemon's database.  Thread-safe; open it once per process."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None, timeout=10.0)
        self._db.row_factory = sqlite3.Row
        mode = self._db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
        if str(mode).lower() != "wal":
            raise sqlite3.OperationalError(f"{self.path}: cannot switch the database to WAL (got {mode})")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.execute("PRAGMA foreign_keys=ON")
        self._db.execute("PRAGMA busy_timeout=10000")
        version = self._db.execute("PRAGMA user_version").fetchone()[0]
        if version > SCHEMA_VERSION:
            raise sqlite3.OperationalError(f"{self.path}: database schema {version} is newer than this "
                                           f"software's ({SCHEMA_VERSION})")
        with self._lock:
            # an older station's database: a copy is kept as it was (<name>.v<N>.bak), then it is upgraded
            self.upgraded_from: int | None = version if 0 < version < SCHEMA_VERSION else None
            self.backup: Path | None = None
            if self.upgraded_from is not None:
                self.backup = self.path.with_name(f"{self.path.name}.v{version}.bak")
                if not self.backup.exists():
                    self._db.execute("VACUUM INTO ?", (str(self.backup),))
            self._db.execute("BEGIN IMMEDIATE")
            try:
                for stmt in _split(_SCHEMA):
                    self._db.execute(stmt)
                upgrade(self._db)
                self._db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
        self._rlock = threading.Lock()
        self._rdb = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None,
                                    timeout=READ_BUSY_TIMEOUT_S)
        self._rdb.row_factory = sqlite3.Row
        self._rdb.execute("PRAGMA query_only=ON")

    def close(self) -> None:
        with self._rlock:
            self._rdb.close()
        with self._lock:
            self._db.close()

    def journal_mode(self) -> str:
        with self._rlock:
            return str(self._rdb.execute("PRAGMA journal_mode").fetchone()[0])

    def ping(self) -> bool:
        try:
            with self._rlock:
                self._rdb.execute("SELECT count(*) FROM runs").fetchone()
            return True
        except sqlite3.Error:
            return False

    # ------------------------------------------------------------------ any statement (station.lab)
    @contextlib.contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """The write connection inside one IMMEDIATE transaction (committed at the end, rolled back
        on an exception): a change and its audit record are taken together or not at all."""
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield self._db
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    @contextlib.contextmanager
    def reading(self) -> Iterator[sqlite3.Connection]:
        """The read connection (read-only), held for a walk over many rows (the audit chain)."""
        with self._rlock:
            self._rdb.execute("BEGIN")  # one snapshot for the whole walk
            try:
                yield self._rdb
            finally:
                self._rdb.execute("COMMIT")

    def query(self, sql: str, args: Sequence[Any] = ()) -> list[dict[str, Any]]:
        """Rows of a read-only statement, as dicts."""
        with self._rlock:
            return [dict(r) for r in self._rdb.execute(sql, tuple(args)).fetchall()]

    # ------------------------------------------------------------------ runs
    def insert_run(self, run: RunRow, db: sqlite3.Connection | None = None) -> None:
        """Insert a run's row (on ``db``, a connection of a transaction already held, if given)."""
        cols = ", ".join(_RUN_COLS)
        marks = ", ".join("?" for _ in _RUN_COLS)
        sql, args = f"INSERT INTO runs ({cols}) VALUES ({marks})", tuple(getattr(run, c) for c in _RUN_COLS)
        if db is not None:
            db.execute(sql, args)
            return
        with self._lock:
            self._db.execute(sql, args)

    def update_run(self, run_id: str, **values: Any) -> None:
        bad = set(values) - set(_RUN_COLS) - {"id"}
        if bad or "id" in values:
            raise KeyError(f"unknown run columns: {sorted(bad | ({'id'} & set(values)))}")
        if not values:
            return
        sets = ", ".join(f"{k} = ?" for k in values)
        with self._lock:
            self._db.execute(f"UPDATE runs SET {sets} WHERE id = ?", (*values.values(), run_id))

    def get_run(self, run_id: str) -> RunRow | None:
        with self._rlock:
            row = self._rdb.execute("SELECT * FROM runs WHERE id = ?", (run_id,)).fetchone()
        return None if row is None else RunRow(**dict(row))

    def list_runs(self, *, limit: int = 100, states: Iterable[str] | None = None) -> list[RunRow]:
        q, args = "SELECT * FROM runs", list[str | int]()
        st = list(states or ())
        if st:
            q += f" WHERE state IN ({', '.join('?' for _ in st)})"
            args.extend(st)
        q += " ORDER BY created DESC, id DESC LIMIT ?"
        args.append(int(limit))
        with self._rlock:
            rows = self._rdb.execute(q, args).fetchall()
        return [RunRow(**dict(r)) for r in rows]

    def list_runs_of(self, transducer_id: str, limit: int = 500) -> list[RunRow]:
        """The newest ``limit`` runs of one transducer, newest first."""
        with self._rlock:
            rows = self._rdb.execute("SELECT * FROM runs WHERE transducer_id = ? ORDER BY created DESC, id DESC "
                                     "LIMIT ?", (transducer_id, int(limit))).fetchall()
        return [RunRow(**dict(r)) for r in rows]

    # ------------------------------------------------------------------ jobs
    def enqueue_job(self, run_id: str, kind: str = "identify") -> int:
        with self._lock:
            cur = self._db.execute("INSERT INTO jobs (run_id, kind, state, created) VALUES (?, ?, 'queued', ?)",
                                   (run_id, kind, time.time()))
            return int(cur.lastrowid or 0)

    def claim_job(self) -> JobRow | None:
        """The oldest queued job, marked running (its attempt counted), or None."""
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                row = self._db.execute("SELECT * FROM jobs WHERE state = 'queued' ORDER BY id LIMIT 1").fetchone()
                if row is None:
                    self._db.execute("COMMIT")
                    return None
                now = time.time()
                self._db.execute("UPDATE jobs SET state = 'running', attempts = attempts + 1, started = ? "
                                 "WHERE id = ?", (now, row["id"]))
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
        job = JobRow(**dict(row))
        job.state, job.attempts, job.started = "running", job.attempts + 1, now
        return job

    def finish_job(self, job_id: int, state: str, error: str = "") -> None:
        if state not in ("done", "failed", "queued"):
            raise ValueError(f"job state {state!r}")
        with self._lock:
            self._db.execute("UPDATE jobs SET state = ?, finished = ?, error = ? WHERE id = ?",
                             (state, None if state == "queued" else time.time(), error, job_id))

    def jobs(self, *, run_id: str | None = None, states: Iterable[str] | None = None) -> list[JobRow]:
        q, args, where = "SELECT * FROM jobs", [], []
        if run_id is not None:
            where.append("run_id = ?")
            args.append(run_id)
        st = list(states or ())
        if st:
            where.append(f"state IN ({', '.join('?' for _ in st)})")
            args.extend(st)
        if where:
            q += " WHERE " + " AND ".join(where)
        q += " ORDER BY id"
        with self._rlock:
            return [JobRow(**dict(r)) for r in self._rdb.execute(q, args).fetchall()]

    def job_counts(self) -> dict[str, int]:
        with self._rlock:
            rows = self._rdb.execute("SELECT state, COUNT(*) FROM jobs GROUP BY state").fetchall()
        out = dict.fromkeys(JOB_STATES, 0)
        out.update({r[0]: int(r[1]) for r in rows})
        return out

    def requeue_running_jobs(self, max_attempts: int) -> tuple[list[JobRow], list[JobRow]]:
        """After a restart: jobs left 'running' go back to the queue, or fail after ``max_attempts``
        (a job that crashed the worker that often will not be tried again).  Returns (requeued, failed)."""
        requeued, failed = [], []
        for job in self.jobs(states=("running",)):
            if job.attempts >= max_attempts:
                self.finish_job(job.id, "failed", f"stopped {job.attempts} times while running; not retried")
                failed.append(job)
            else:
                self.finish_job(job.id, "queued")
                requeued.append(job)
        return requeued, failed

    # ------------------------------------------------------------------ emergency stops
    def raise_estop(self, source: str, detail: str, raised: float | None = None) -> EStopRow:
        with self._lock:
            cur = self._db.execute("INSERT INTO estops (raised, source, detail) VALUES (?, ?, ?)",
                                   (raised or time.time(), source, detail))
            row = self._db.execute("SELECT * FROM estops WHERE id = ?", (cur.lastrowid,)).fetchone()
        return EStopRow(**dict(row))

    def open_estops(self) -> list[EStopRow]:
        """Emergency stops not yet acknowledged, oldest first."""
        with self._rlock:
            rows = self._rdb.execute("SELECT * FROM estops WHERE acknowledged IS NULL ORDER BY id").fetchall()
        return [EStopRow(**dict(r)) for r in rows]

    def acknowledge_estops(self, by: str, note: str = "") -> list[EStopRow]:
        """Mark every open emergency stop acknowledged by ``by`` now; returns them."""
        now = time.time()
        with self._lock:
            self._db.execute("UPDATE estops SET acknowledged = ?, acknowledged_by = ?, note = ? "
                             "WHERE acknowledged IS NULL", (now, by, note))
            rows = self._db.execute("SELECT * FROM estops WHERE acknowledged = ? ORDER BY id", (now,)).fetchall()
        return [EStopRow(**dict(r)) for r in rows]

    def last_estop(self) -> EStopRow | None:
        with self._rlock:
            row = self._rdb.execute("SELECT * FROM estops ORDER BY id DESC LIMIT 1").fetchone()
        return None if row is None else EStopRow(**dict(row))
