"""The daemon's health: each device link, the database, the workers, the run on the rig."""

from __future__ import annotations

import time
from typing import Any

from station.service import worker
from station.service.disk import RecordingsDisk
from station.service.latch import EStopLatch
from station.service.riglink import RigLink
from station.service.store import Store


def health(link: RigLink, store: Store, pool: worker.WorkerPool, latch: EStopLatch, disk: RecordingsDisk, *,
           workers: int, sim: bool, active_run: str | None, started_at: float,
           unrecorded: dict[str, str] | None = None) -> dict[str, Any]:
    """``status`` is ``ok`` only with the rig connected over healthy links, the database answering
    and taking every job outcome (``unrecorded``: run id -> an outcome it refused, and why), no
    emergency stop latched and room on the recordings disk."""
    rig = link.rig
    links = rig.health() if rig is not None else {
        "motor": {"connected": False, "watchdog_error": None},
        "daq": {"link_error": link.error}, "simulated": sim}
    unrecorded = dict(unrecorded or {})
    counts = store.job_counts()
    db_ok = store.ping()
    rig_ok = rig is not None and link.healthy(rig)
    estop = latch.state() if db_ok else {"latched": None}
    space = disk.state()
    db_ok = db_ok and not unrecorded  # answering, but not taking what it is given
    return {"status": "ok" if rig_ok and db_ok and not estop["latched"] and space["ok"] else "degraded",
            "estop": estop, "disk": space,
            "rig": {"connected": rig is not None, "error": link.error,
                    "description": rig.description if rig is not None else "", **links},
            "database": {"ok": db_ok, "journal_mode": store.journal_mode() if db_ok else None},
            "worker": {"processes": workers, "started": pool.started, "crashes": pool.crashes, "jobs": counts,
                       "unrecorded": unrecorded},
            "active_run": active_run,
            "uptime_s": time.time() - started_at}
