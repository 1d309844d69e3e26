"""The daemon's health: each device link, the drive's last read-back, the database, the workers, the
run on the rig."""

from __future__ import annotations

import time
from typing import Any

from station.lab.store import JOB_STATES, Store
from station.service import worker
from station.service.db import DbAccess
from station.service.disk import RecordingsDisk
from station.service.errors import DatabaseBusyError
from station.service.latch import EStopLatch
from station.service.riglink import RigLink

DB_HEALTH_TIMEOUT_S = 1.0
DB_STALL_S = 1.0  # a write waiting longer than this for the database makes it not ok


async def database_state(db: DbAccess) -> dict[str, Any]:
    """The database as /health shows it, read with a short bound (a locked database is reported,
    never waited for): ok, journal mode, job counts, writes waiting and why."""

    def read(store: Store) -> tuple[bool, str | None, dict[str, int]]:
        ok = store.ping()
        return ok, store.journal_mode() if ok else None, store.job_counts() if ok else {}

    error = db.last_error
    stalled = db.stalled_s
    if error is None and stalled > DB_STALL_S:
        error = f"a write has waited {stalled:.1f} s for the database (locked by another process?)"
    try:
        ok, mode, jobs = await db.read(read, timeout_s=DB_HEALTH_TIMEOUT_S)
    except DatabaseBusyError as exc:
        ok, mode, jobs, error = False, None, {}, error or str(exc)
    backlog = db.backlog
    return {"ok": ok and error is None, "journal_mode": mode, "pending_writes": backlog, "error": error,
            "jobs": {**dict.fromkeys(JOB_STATES, 0), **jobs}}


def health(link: RigLink, database: dict[str, Any], pool: worker.WorkerPool, latch: EStopLatch,
           disk: RecordingsDisk, *, workers: int, sim: bool, active_run: str | None,
           started_at: float, unrecorded: dict[str, str] | None = None) -> dict[str, Any]:
    """``status`` is ``ok`` only with the rig connected over healthy links, the drive not reported
    turning after a stop, the database answering and taking every write (``unrecorded``: run id ->
    a job outcome it has not taken yet, and why), no emergency stop latched and room on the
    recordings disk."""
    rig = link.rig
    dev = link.error_device  # a connection failure is shown under its device only (both if unknown)
    links = rig.health() if rig is not None else {
        "motor": {"connected": False, "watchdog_error": None, "link_error": link.error if dev != "daq" else None},
        "daq": {"link_error": link.error if dev != "motor" else None}, "simulated": sim}
    unrecorded = dict(unrecorded or {})
    rig_ok = rig is not None and link.healthy(rig)
    estop = latch.state()
    space = disk.state()
    drive = link.drive.to_dict() if link.drive is not None else None
    drive_ok = drive is None or drive["standstill"] is not False
    jobs = database.pop("jobs")
    database["ok"] = database["ok"] and not unrecorded  # answering, but not taking what it is given
    ok = rig_ok and drive_ok and database["ok"] and not estop["latched"] and space["ok"]
    return {"status": "ok" if ok else "degraded",
            "estop": estop, "disk": space, "drive": drive,
            "rig": {"connected": rig is not None, "error": link.error,
                    "description": rig.description if rig is not None else "", **links},
            "database": database,
            "worker": {"processes": workers, "started": pool.started, "crashes": pool.crashes, "jobs": jobs,
                       "unrecorded": unrecorded},
            "active_run": active_run,
            "uptime_s": time.time() - started_at}
