"""The emergency-stop latch: after ``POST /stop``, the page's button, the motor controller's
emergency-stop fault or a drive that did not come to rest, no run starts until an operator
acknowledges it.  Both the stop and the acknowledgement (who, when, a note) are rows in the database
and lines in the log, so the latch survives a restart of the daemon.

The latch itself is in memory (loaded from the database at the start): tripping it never waits on
the database, whose record follows through the retrying writer (``db.py``) when it can.  An
acknowledgement is refused while the database cannot record it."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from typing import Any

from station.lab import audit
from station.lab.store import EStopRow, Store
from station.service.db import DbAccess

log = logging.getLogger(__name__)


def _iso(ts: float | None) -> str | None:
    return None if ts is None else datetime.fromtimestamp(ts, UTC).isoformat(timespec="milliseconds")


class EStopLatch:
    """Open emergency stops (oldest first) and the last acknowledgement, in memory."""

    def __init__(self, db: DbAccess) -> None:
        self.db = db
        self._open: list[EStopRow] = []
        self._open_lock = threading.Lock()  # trips come from the rig thread and the stop port's thread too
        self._last_ack: tuple[float, str] | None = None  # (when, by)

    def load(self) -> None:
        """At the start, before anything is served: the stops left open by the previous daemon."""
        self._open = self.db.store.open_estops()
        last = self.db.store.last_estop()
        if last is not None and last.acknowledged is not None:
            self._last_ack = (last.acknowledged, last.acknowledged_by or "")

    @property
    def latched(self) -> bool:
        return bool(self._open)

    def trip(self, source: str, detail: str, who: str | Callable[[Store], str] = audit.SYSTEM) -> None:
        """Latch now; the database's record and the audit entry follow (retried until taken).
        ``who``: the user who asked for the stop, or a function that finds them in the database when
        the record is written (never before the stop: the stop waits on nothing)."""
        log.warning("emergency stop latched (source %s): %s", source, detail)
        raised = time.time()
        with self._open_lock:
            self._open.append(EStopRow(0, raised, source, detail, None, None, ""))

        def record(store: Store) -> None:
            row = store.raise_estop(source, detail, raised)
            name = who(store) if callable(who) else who
            audit.append(store, name, audit.ESTOP_RAISED, "station", {"estop": row.id, "source": source,
                                                                      "detail": detail})
        self.db.post(record)

    async def acknowledge(self, by: str, note: str = "") -> list[EStopRow]:
        """Record the acknowledgement (DatabaseBusyError if the database cannot take it now: the
        latch stays) and release the stops it covers."""
        with self._open_lock:
            covered = list(self._open)

        def ack(store: Store) -> list[EStopRow]:
            rows = store.acknowledge_estops(by, note)
            audit.append(store, by, audit.ESTOP_ACKNOWLEDGED, "station",
                         {"note": note, "estops": [r.id for r in rows]})
            return rows
        rows = await self.db.call(ack)
        with self._open_lock:  # a stop tripped meanwhile (on another thread) stays latched
            self._open = [r for r in self._open if r not in covered]
        if rows:
            self._last_ack = (rows[-1].acknowledged or time.time(), by)
            log.warning("emergency stop acknowledged by %s (%d stop(s) since %s)%s", by, len(rows),
                        _iso(rows[0].raised), f": {note}" if note else "")
        else:
            log.info("acknowledgement by %s with no emergency stop latched", by)
        return rows

    def refusal(self) -> str | None:
        """Why a run may not start now (None: it may)."""
        if not self._open:
            return None
        first = self._open[0]
        return (f"emergency stop latched since {_iso(first.raised)} ({first.source}: {first.detail}); an operator "
                "must acknowledge it first (POST /stop/acknowledge, the page's acknowledge button or `station ack`)")

    def state(self) -> dict[str, Any]:
        """For /health and the page."""
        rows = self._open
        out: dict[str, Any] = {"latched": bool(rows), "since": None, "source": None, "detail": None,
                               "count": len(rows), "last_acknowledged": None, "last_acknowledged_by": None}
        if rows:
            out.update(since=_iso(rows[0].raised), source=rows[-1].source, detail=rows[-1].detail)
        if self._last_ack is not None:
            out.update(last_acknowledged=_iso(self._last_ack[0]), last_acknowledged_by=self._last_ack[1])
        return out
