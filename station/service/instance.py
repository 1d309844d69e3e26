"""One station per recordings folder, and a database that can be opened, checked before anything else.

A daemon (and ``station calibrate``) holds an exclusive ``flock`` on ``<recordings>/.station.lock``
for its whole life, taken before the start-up recovery, the database or a device is touched.  A
second process on the same folder is refused at once with a message naming the holder (its PID,
host and address, from the lock file); it touches nothing.  The lock is the kernel's: it goes with
the process however it ends (``kill -9`` included), so a lock file left behind never blocks a
start; a clean end removes it.  Worker processes do not inherit it (the descriptor is close-on-exec).

``check_database`` opens the daemon's SQLite file before the daemon starts: a damaged, foreign or
locked file is one message naming the file and the fix, never a traceback.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import logging
import os
import socket
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any, ClassVar

from station.errors import StationError

log = logging.getLogger(__name__)

LOCK_NAME = ".station.lock"


class StationBusyError(StationError):
    """Another process already runs a station on this recordings folder."""


class DatabaseUnusableError(StationError):
    """The station's database cannot be opened (damaged, not a database, locked, unreadable)."""


class InstanceLock:
    """The exclusive lock on one recordings folder (module docstring).  Re-entrant within a process
    (the ``serve`` command and the daemon's RunManager both take it; the last release frees it)."""

    _held: ClassVar[dict[Path, InstanceLock]] = {}
    _guard: ClassVar[threading.Lock] = threading.Lock()

    def __init__(self, path: Path, fd: int) -> None:
        self.path = path
        self._fd = fd
        self._users = 0
        self.info: dict[str, Any] = {}

    @classmethod
    def acquire(cls, recordings_dir: Path, what: str, **info: Any) -> InstanceLock:
        """The lock of ``recordings_dir`` for this process, with ``info`` (e.g. host, port) written
        into the lock file for whoever is refused; raises StationBusyError naming the holder."""
        path = (Path(recordings_dir).resolve() / LOCK_NAME)
        with cls._guard:
            lock = cls._held.get(path)
            if lock is None:
                lock = cls(path, _lock_or_refuse(path, what))
                cls._held[path] = lock
                lock.update(what=what, pid=os.getpid(), hostname=socket.gethostname(), since=time.time(), **info)
            lock._users += 1
            return lock

    def update(self, **info: Any) -> None:
        """Add to what the lock file says (the address once the daemon listens)."""
        self.info.update({k: v for k, v in info.items() if v is not None})
        data = json.dumps(self.info).encode()
        try:
            os.ftruncate(self._fd, 0)
            os.pwrite(self._fd, data, 0)
        except OSError as exc:  # a full disk: the lock holds all the same, only the note is missing
            log.warning("%s: cannot write the lock note: %s", self.path, exc.strerror)

    def release(self) -> None:
        with self._guard:
            if self._users <= 0:
                return
            self._users -= 1
            if self._users > 0:
                return
            self._held.pop(self.path, None)
            with contextlib.suppress(OSError):  # nothing left behind (the next holder checks the inode)
                self.path.unlink()
            os.close(self._fd)  # closing the descriptor releases the flock

    def __enter__(self) -> InstanceLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _lock_or_refuse(path: Path, what: str) -> int:
    for _ in range(10):
        fd = _try_lock(path, what)
        try:  # the holder before us may have removed the file as we opened it: lock the one in place
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)
    raise StationBusyError(f"{path}: the lock file keeps being replaced; is another station starting and stopping?")


def _try_lock(path: Path, what: str) -> int:
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError as exc:
        raise StationBusyError(f"{path}: cannot create the station's lock file ({exc.strerror}); the "
                               "recordings folder must be writable") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        holder = _holder(fd)
        os.close(fd)
        if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
            raise StationBusyError(f"{path}: cannot lock the recordings folder ({exc.strerror})") from None
        raise StationBusyError(
            f"another station already uses the recordings folder {path.parent}: {holder}. {what} refuses to "
            "start and has touched nothing (no recovery, no device opened); stop the other one first, or "
            f"give this one its own station.recordings_dir (lock file {path})") from None
    return fd


def _holder(fd: int) -> str:
    """Who holds the lock, from the note in the lock file."""
    try:
        info = json.loads(os.pread(fd, 4096, 0) or b"{}")
    except (OSError, ValueError):
        info = {}
    if not isinstance(info, dict) or "pid" not in info:
        return "a process whose note cannot be read"
    parts = [f"{info.get('what', 'a station process')} with PID {info['pid']}"]
    if info.get("hostname"):
        parts.append(f"on {info['hostname']}")
    if info.get("port"):
        host = str(info.get("host", "?"))
        parts.append(f"listening on http://{f'[{host}]' if ':' in host else host}:{info['port']}/")
    if isinstance(info.get("since"), int | float):
        parts.append("since " + time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(info["since"])))
    return " ".join(parts)


# --------------------------------------------------------------------------------------- the database
def check_database(path: Path) -> None:
    """Open the daemon's database as the daemon will, and check it (``PRAGMA quick_check``, a write
    lock for a moment); raises DatabaseUnusableError naming the file and the fix.  A missing file
    is fine (it is created)."""
    if not path.exists():
        return
    try:
        db = sqlite3.connect(f"file:{path}?mode=rw", uri=True, timeout=1.0, isolation_level=None)
    except sqlite3.Error as exc:
        raise _unusable(path, exc) from None
    try:
        rows = db.execute("PRAGMA quick_check").fetchall()
        if [tuple(r) for r in rows] != [("ok",)]:
            raise _damaged(path, "; ".join(str(r[0]) for r in rows[:3]))
        db.execute("BEGIN IMMEDIATE")
        db.execute("ROLLBACK")
    except sqlite3.Error as exc:
        raise _unusable(path, exc) from None
    finally:
        db.close()


def _unusable(path: Path, exc: sqlite3.Error) -> DatabaseUnusableError:
    text = str(exc)
    if "locked" in text or "busy" in text:
        return DatabaseUnusableError(
            f"the station database {path} is locked by another process (an open sqlite3 session, a backup "
            "tool, another station): close that program and start again")
    if "readonly" in text or "unable to open" in text or "permission" in text.lower():
        return DatabaseUnusableError(f"the station database {path} cannot be opened for writing ({text}): "
                                     "check its permissions and those of its folder")
    return _damaged(path, text)


def _damaged(path: Path, detail: str) -> DatabaseUnusableError:
    return DatabaseUnusableError(
        f"the station database {path} is damaged or not a station database ({detail}). Fix: move it aside "
        f"with its -wal and -shm files (mv {path} {path}.damaged), then start again: a new database is made "
        "and the recordings stay where they are; the old database's runs can be salvaged with "
        f"'sqlite3 {path}.damaged .recover'")
