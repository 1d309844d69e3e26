"""The recordings disk: free space, and a reserve file that makes a full disk survivable.

HDF5 cannot finish a file after a write failed for lack of space (it still holds dirty chunks and
metadata to write; closing then fails, and the library may crash later).  So the daemon keeps a
*reserve file* of ``RESERVE_FILE_BYTES`` in the recordings folder.  When a run's recording hits a
full disk (ENOSPC), the procedure releases the reserve first: the recording is then closed with its
stop document and reason, the database takes the run's final state, and the space is there for
both.  ``/health`` says ``degraded`` until there is room again for the configured reserve
(``station.min_free_mb``) and the reserve file, which is then made anew.
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
import threading
from pathlib import Path
from typing import Any

from station.errors import StationError
from station.recording.writer import is_disk_full

__all__ = ["DiskSpaceError", "RecordingsDisk", "is_disk_full"]

log = logging.getLogger(__name__)

RESERVE_FILE = ".station-reserve"
RESERVE_FILE_BYTES = 8 * 2**20  # > the writer's chunk cache (1.3 MB) + metadata + the database's WAL growth


class DiskSpaceError(StationError):
    """The recordings disk has no room for a run (503)."""


def release_file(path: Path) -> int:
    """Delete the reserve file ``path`` (a recording hit a full disk); the bytes freed, 0 if it was not there."""
    try:
        size = path.stat().st_size
        path.unlink()
    except FileNotFoundError:
        return 0
    return size


class RecordingsDisk:
    def __init__(self, directory: Path, min_free_bytes: int, reserve_file_bytes: int = RESERVE_FILE_BYTES) -> None:
        self.directory = directory
        self.min_free_bytes = min_free_bytes
        self.reserve_file_bytes = reserve_file_bytes
        self.path = directory / RESERVE_FILE
        self._lock = threading.Lock()
        self.released = 0  # times the reserve was used

    def free_bytes(self) -> int:
        try:
            return int(shutil.disk_usage(self.directory).free)
        except OSError:
            return 0

    def ensure_reserve(self) -> bool:
        """Make the reserve file if it is missing and the disk has room for it beyond the configured
        reserve; True when it exists."""
        with self._lock:
            if self.path.exists():
                return True
            if self.free_bytes() < self.reserve_file_bytes + self.min_free_bytes:
                return False
            tmp = self.path.with_name(self.path.name + ".new")
            try:
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
                try:
                    try:
                        os.posix_fallocate(fd, 0, self.reserve_file_bytes)
                    except OSError as exc:
                        if exc.errno != errno.EOPNOTSUPP and exc.errno != errno.EINVAL:
                            raise
                        block = b"\0" * 2**20
                        for _ in range(self.reserve_file_bytes // len(block)):
                            os.write(fd, block)
                    os.fsync(fd)
                finally:
                    os.close(fd)
                os.replace(tmp, self.path)
                log.info("recordings disk: reserve file of %.0f MiB in place", self.reserve_file_bytes / 2**20)
                return True
            except OSError as exc:
                log.warning("recordings disk: cannot make the reserve file: %s", exc)
                tmp.unlink(missing_ok=True)
                return False

    def release_reserve(self) -> int:
        """Free the reserve file (a recording hit a full disk); returns the bytes freed."""
        with self._lock:
            size = release_file(self.path)
            if not size:
                return 0
            self.released += 1
            log.error("recordings disk full: reserve file of %.0f MiB released to close the recording "
                      "and record the run's end", size / 2**20)
            return size

    def state(self) -> dict[str, Any]:
        have = self.ensure_reserve()
        free = self.free_bytes()
        ok = have and free >= self.min_free_bytes
        return {"ok": ok, "free_bytes": free, "reserve_bytes": self.min_free_bytes,
                "reserve_file": have, "reserve_used": self.released,
                "detail": None if ok else (f"recordings disk full: {free / 2**20:.1f} MiB free in {self.directory}; "
                                           f"needs {self.min_free_bytes / 2**20:.1f} MiB reserve and a "
                                           f"{self.reserve_file_bytes / 2**20:.0f} MiB reserve file")}

    def check_for_run(self) -> None:
        st = self.state()
        if not st["ok"]:
            raise DiskSpaceError(f"no run can start: {st['detail']}")
