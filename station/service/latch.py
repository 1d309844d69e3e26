"""The emergency-stop latch: after ``POST /stop``, the page's button or the motor controller's
emergency-stop fault no run starts until an operator acknowledges it.  Both the stop and the
acknowledgement (who, when, a note) are rows in the database and lines in the log, so the latch
survives a restart of the daemon."""

from __future__ import annotations

import logging
import sqlite3
import time
from datetime import UTC, datetime
from typing import Any

from station.service.store import EStopRow, Store

log = logging.getLogger(__name__)


def _iso(ts: float | None) -> str | None:
    return None if ts is None else datetime.fromtimestamp(ts, UTC).isoformat(timespec="milliseconds")


class EStopLatch:
    """Latched state in the database; a stop the database cannot take (full disk) is held in memory
    (still latched) and written at the next occasion."""

    def __init__(self, store: Store) -> None:
        self.store = store
        self._unsaved: list[tuple[float, str, str]] = []

    def _flush(self) -> None:
        while self._unsaved:
            raised, source, detail = self._unsaved[0]
            try:
                self.store.raise_estop(source, detail, raised)
            except sqlite3.Error:
                return
            self._unsaved.pop(0)

    def _open(self) -> list[EStopRow]:
        self._flush()
        rows = self.store.open_estops()
        return rows + [EStopRow(0, r, s, d, None, None, "") for r, s, d in self._unsaved]

    @property
    def latched(self) -> bool:
        return bool(self._open())

    def trip(self, source: str, detail: str) -> EStopRow | None:
        log.warning("emergency stop latched (source %s): %s", source, detail)
        try:
            self._flush()
            return self.store.raise_estop(source, detail)
        except sqlite3.Error as exc:
            log.error("the database did not take the emergency stop (%s); latched in memory", exc)
            self._unsaved.append((time.time(), source, detail))
            return None

    def acknowledge(self, by: str, note: str = "") -> list[EStopRow]:
        self._flush()
        if self._unsaved:
            raise sqlite3.OperationalError("the database cannot record the acknowledgement now (disk full?)")
        rows = self.store.acknowledge_estops(by, note)
        if rows:
            log.warning("emergency stop acknowledged by %s (%d stop(s) since %s)%s", by, len(rows),
                        _iso(rows[0].raised), f": {note}" if note else "")
        else:
            log.info("acknowledgement by %s with no emergency stop latched", by)
        return rows

    def refusal(self) -> str | None:
        """Why a run may not start now (None: it may)."""
        rows = self._open()
        if not rows:
            return None
        first = rows[0]
        return (f"emergency stop latched since {_iso(first.raised)} ({first.source}: {first.detail}); an operator "
                "must acknowledge it first (POST /stop/acknowledge, the page's acknowledge button or `station ack`)")

    def state(self) -> dict[str, Any]:
        """For /health and the page."""
        rows = self._open()
        last = self.store.last_estop()
        out: dict[str, Any] = {"latched": bool(rows), "since": None, "source": None, "detail": None,
                               "count": len(rows), "last_acknowledged": None, "last_acknowledged_by": None}
        if rows:
            out.update(since=_iso(rows[0].raised), source=rows[-1].source, detail=rows[-1].detail)
        if last is not None and last.acknowledged is not None:
            out.update(last_acknowledged=_iso(last.acknowledged), last_acknowledged_by=last.acknowledged_by)
        return out
