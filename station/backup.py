"""Backup and restore of a station's data: the database, the recordings, the results stored beside
them, the issued certificates and public keys (``station backup DEST``, ``station restore SRC``).

A backup is a folder: ``station.db`` (a consistent copy by SQLite's online backup API, taken while
the station runs), every other file of the recordings folder under ``data/`` as it is, and
``MANIFEST.json``, written last, with each file's SHA-256 and size.  Left out: recordings still
being written (``*.partial``: listed as ``in_progress``; a closed recording is never written again,
so it is copied as it is), the database's own WAL files, the station's lock and disk-reserve files,
temporaries, and private keys (``*.key``, ``*.pem`` without ``.pub``; only keys' public parts go).

A restore checks the whole backup first (the manifest present, every file there with its hash and
size, the database's integrity) and refuses a damaged or partial one naming what is wrong; then it
copies into an empty folder (through a temporary folder beside it, renamed at the end), so a
station never starts on half a restore.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from station import __version__
from station.errors import StationError

FORMAT = "sinecal-backup"
VERSION = 1
MANIFEST = "MANIFEST.json"
DATABASE = "station.db"
DATA = "data"
SKIP_NAMES = {".station.lock", ".station-reserve"}
SKIP_SUFFIXES = (".partial", ".tmp", "-wal", "-shm", "-journal", ".key")
CHUNK = 1 << 20


class BackupError(StationError):
    """A backup that cannot be made, or one that is damaged or partial (the message names what)."""


@dataclass(frozen=True)
class BackupReport:
    """What a backup or restore did: the folder, the files (with the database) and their bytes, the
    recordings left out because they were being written."""

    folder: Path
    files: int
    bytes: int
    in_progress: tuple[str, ...] = field(default=())


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        while chunk := f.read(CHUNK):
            h.update(chunk)
    return h.hexdigest()


def _skipped(rel: Path, database: Path, root: Path) -> bool:
    name = rel.name
    if name in SKIP_NAMES or name.endswith(SKIP_SUFFIXES) or (name.endswith(".pem") and ".pub" not in name):
        return True
    full = (root / rel).resolve()
    return full == database or (full.name.startswith(database.name) and full.parent == database.parent)


def backup(recordings_dir: Path, database: Path, dest: Path) -> BackupReport:
    """Copy the station's data to ``dest`` (a new or empty folder), consistently while it runs."""
    root, database, dest = Path(recordings_dir).resolve(), Path(database).resolve(), Path(dest).resolve()
    if dest.exists() and any(dest.iterdir()):
        raise BackupError(f"{dest} is not empty: back up into a new or empty folder")
    if dest == root or root in dest.parents:
        raise BackupError(f"{dest} is inside the recordings folder {root}: back up elsewhere")
    if not database.exists():
        raise BackupError(f"no station database at {database}")
    dest.mkdir(parents=True, exist_ok=True)
    files: dict[str, dict[str, Any]] = {}
    # the database first: its copy names the runs and certificates whose files must be there
    src = sqlite3.connect(f"file:{database}?mode=ro", uri=True, timeout=30.0)
    try:
        out = sqlite3.connect(dest / DATABASE)
        try:
            src.backup(out)  # SQLite's online backup: a consistent snapshot while the station writes
        finally:
            out.close()
    finally:
        src.close()
    files[DATABASE] = {"sha256": sha256_of(dest / DATABASE), "bytes": (dest / DATABASE).stat().st_size}
    in_progress = []
    for path in sorted(root.rglob("*")):
        if not path.is_file() or path.is_symlink():
            continue
        rel = path.relative_to(root)
        if path.name.endswith(".partial"):
            in_progress.append(rel.as_posix())
            continue
        if _skipped(rel, database, root):
            continue
        target = dest / DATA / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        h = hashlib.sha256()
        with path.open("rb") as f, target.open("wb") as g:  # hashed as copied: the copy is what is listed
            while chunk := f.read(CHUNK):
                h.update(chunk)
                g.write(chunk)
        files[f"{DATA}/{rel.as_posix()}"] = {"sha256": h.hexdigest(), "bytes": target.stat().st_size}
    manifest = {"format": FORMAT, "version": VERSION, "software": __version__,
                "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "source": str(root),
                "database": DATABASE, "files": files, "in_progress": in_progress}
    tmp = dest / f"{MANIFEST}.tmp"
    with tmp.open("w") as f:
        json.dump(manifest, f, indent=1, sort_keys=True)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, dest / MANIFEST)  # last: a backup without its manifest is partial
    return BackupReport(dest, len(files), sum(int(v["bytes"]) for v in files.values()), tuple(in_progress))


def check_backup(src: Path) -> dict[str, Any]:
    """The manifest of the backup at ``src`` once every file checks out (BackupError naming what is
    missing, altered or damaged otherwise)."""
    src = Path(src).resolve()
    try:
        manifest = json.loads((src / MANIFEST).read_text())
    except FileNotFoundError:
        raise BackupError(f"{src}: no {MANIFEST}: not a backup, or a partial one (it is written last)") from None
    except (OSError, ValueError) as exc:
        raise BackupError(f"{src / MANIFEST}: unreadable ({exc})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT or not isinstance(manifest.get("files"),
                                                                                              dict):
        raise BackupError(f"{src / MANIFEST}: not a {FORMAT} manifest")
    if int(manifest.get("version", 0)) > VERSION:
        raise BackupError(f"{src}: backup format {manifest.get('version')} is newer than this software's ({VERSION})")
    problems = []
    for rel, entry in manifest["files"].items():
        p = (src / rel).resolve()
        if src not in p.parents:
            problems.append(f"{rel}: outside the backup")
        elif not p.is_file():
            problems.append(f"{rel}: missing")
        elif p.stat().st_size != entry.get("bytes") or sha256_of(p) != entry.get("sha256"):
            problems.append(f"{rel}: altered or damaged (its SHA-256 or size differs from the manifest's)")
    if DATABASE not in manifest["files"]:
        problems.append(f"{DATABASE}: not in the manifest")
    if problems:
        shown = "; ".join(problems[:5]) + (f"; and {len(problems) - 5} more" if len(problems) > 5 else "")
        raise BackupError(f"{src}: the backup is damaged or partial: {shown}")
    db = sqlite3.connect(f"file:{src / DATABASE}?mode=ro", uri=True)
    try:
        ok = db.execute("PRAGMA integrity_check").fetchone()[0]
    except sqlite3.DatabaseError as exc:
        ok = str(exc)
    finally:
        db.close()
    if ok != "ok":
        raise BackupError(f"{src / DATABASE}: the database copy is damaged ({ok})")
    return dict(manifest)


def restore(src: Path, recordings_dir: Path, database: Path | None = None) -> BackupReport:
    """Restore the backup at ``src`` into ``recordings_dir`` (new or empty); the database goes to
    ``database`` (default ``<recordings_dir>/station.db``).  Checks the whole backup first."""
    src, root = Path(src).resolve(), Path(recordings_dir).resolve()
    manifest = check_backup(src)
    db_target = Path(database).resolve() if database is not None else root / DATABASE
    if root.exists() and any(root.iterdir()):
        raise BackupError(f"{root} is not empty: restore into a new or empty folder (a station's data is never "
                          "overwritten)")
    if db_target.exists():
        raise BackupError(f"{db_target} exists: restore where there is no station database")
    staging = root.with_name(f".{root.name}.restoring")
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    total = 0
    try:
        for rel, entry in manifest["files"].items():
            target = staging / (DATABASE if rel == DATABASE else Path(rel).relative_to(DATA))
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src / rel, target)
            if sha256_of(target) != entry["sha256"]:
                raise BackupError(f"{target}: the copy differs from the backup (the disk?)")
            total += int(entry["bytes"])
        if db_target != root / DATABASE:
            db_target.parent.mkdir(parents=True, exist_ok=True)
            shutil.move(str(staging / DATABASE), db_target)
        if root.exists():
            root.rmdir()  # empty, checked above
        os.replace(staging, root)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return BackupReport(root, len(manifest["files"]), total, tuple(manifest.get("in_progress", ())))
