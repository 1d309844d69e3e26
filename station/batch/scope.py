"""Which recordings a batch re-identifies: the complete runs in a recordings folder, filtered by
start time and transducer.  Reads root attributes only (docs/recording-format.md), not the samples."""

from __future__ import annotations

import logging
from datetime import UTC, datetime
from pathlib import Path

import h5py

from station.errors import BadInputError

log = logging.getLogger(__name__)
FORMAT_NAME = "sinecal-recording"


def parse_when(text: str) -> datetime:
    """An ISO 8601 date or date-time; without a time zone it is UTC."""
    try:
        t = datetime.fromisoformat(text.strip())
    except ValueError:
        raise BadInputError(f"--since: an ISO 8601 date or date-time expected (e.g. 2025-03-12 or "
                            f"2025-03-12T09:00), got {text!r}") from None
    return t if t.tzinfo else t.replace(tzinfo=UTC)


def _attrs(path: Path) -> dict[str, str]:
    with h5py.File(path, "r") as f:
        return {k: str(f.attrs.get(k, "")) for k in ("format", "transducer_id", "start_time", "exit_status")}


def select_recordings(folder: Path, *, since: datetime | None = None,
                      transducer: str | None = None) -> tuple[list[Path], list[str]]:
    """(recordings in scope sorted by start time, notes on the files left out).

    In scope: ``*.h5`` in ``folder`` (not its sub-folders) with exit status "completed", started at
    or after ``since``, of transducer ``transducer``.  ``*.h5.partial`` files (a run being written,
    or cut off by a crash) are left out with a note; so are unreadable files and runs that did not
    complete (aborted, failed, interrupted)."""
    if not folder.is_dir():
        raise BadInputError(f"{folder}: recordings folder not found")
    chosen: list[tuple[datetime, Path]] = []
    notes: list[str] = []
    for p in sorted(folder.resolve().iterdir()):
        if p.name.endswith(".h5.partial"):
            notes.append(f"{p.name}: skipped, partial recording (being written, or cut off: recover it first)")
            continue
        if not p.name.endswith(".h5") or not p.is_file():
            continue
        try:
            a = _attrs(p)
        except OSError as exc:
            notes.append(f"{p.name}: skipped, not readable ({exc})")
            continue
        if a["format"] != FORMAT_NAME:
            notes.append(f"{p.name}: skipped, not a sinecal recording")
            continue
        if transducer is not None and a["transducer_id"] != transducer:
            continue
        try:
            start = parse_when(a["start_time"])
        except BadInputError:
            notes.append(f"{p.name}: skipped, start_time {a['start_time']!r} is not a date")
            continue
        if since is not None and start < since:
            continue
        if a["exit_status"] != "completed":
            notes.append(f"{p.name}: skipped, exit status {a['exit_status']!r} (only completed runs are "
                         "re-identified)")
            continue
        chosen.append((start, p))
    chosen.sort()
    for n in notes:
        log.info("batch scope: %s", n)
    return [p for _, p in chosen], notes
