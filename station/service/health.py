"""The daemon's health: each device link, the database, the workers, the run on the rig."""

from __future__ import annotations

import time
from typing import Any

from station.service import worker
from station.service.riglink import RigLink
from station.service.store import Store


def health(link: RigLink, store: Store, pool: worker.WorkerPool, *, workers: int, sim: bool,
           active_run: str | None, started_at: float) -> dict[str, Any]:
    """``status`` is ``ok`` only with the rig connected over healthy links and the database answering."""
    rig = link.rig
    links = rig.health() if rig is not None else {
        "motor": {"connected": False, "watchdog_error": None},
        "daq": {"link_error": link.error}, "simulated": sim}
    counts = store.job_counts()
    db_ok = store.ping()
    rig_ok = rig is not None and link.healthy(rig)
    return {"status": "ok" if rig_ok and db_ok else "degraded",
            "rig": {"connected": rig is not None, "error": link.error,
                    "description": rig.description if rig is not None else "", **links},
            "database": {"ok": db_ok, "journal_mode": store.journal_mode() if db_ok else None},
            "worker": {"processes": workers, "started": pool.started, "crashes": pool.crashes, "jobs": counts},
            "active_run": active_run,
            "uptime_s": time.time() - started_at}
