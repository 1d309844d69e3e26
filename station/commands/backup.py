"""``station backup DEST`` and ``station restore SRC``: the station's data copied consistently while
it runs, and brought back into an empty folder after the whole backup checked out (``station.backup``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from station.service.settings import ServiceSettings


def register(sub: argparse._SubParsersAction) -> None:
    b = sub.add_parser("backup", help="copy the database, recordings, results and certificates to DEST "
                       "(consistent while the station runs; a manifest with hashes)")
    b.add_argument("dest", type=Path, metavar="DEST", help="a new or empty folder")
    b.add_argument("--config", type=Path, default=None, help="station YAML (its recordings folder and database)")
    b.set_defaults(handler=_backup)
    r = sub.add_parser("restore", help="check a backup whole, then restore it into an empty recordings folder")
    r.add_argument("src", type=Path, metavar="SRC", help="a folder made by station backup")
    r.add_argument("--config", type=Path, default=None, help="station YAML (where to restore)")
    r.add_argument("--into", type=Path, default=None, help="the recordings folder to restore into (default: "
                   "the configuration's; it must be new or empty)")
    r.add_argument("--check", action="store_true", help="only check the backup; restore nothing")
    r.set_defaults(handler=_restore)


def _settings(config: Path | None) -> ServiceSettings:
    from station.service.settings import load_settings

    return load_settings(config, sim=True)


def _backup(args: argparse.Namespace) -> int:
    from station.backup import backup

    s = _settings(args.config)
    rep = backup(s.recordings_dir, s.database, args.dest)
    print(f"backed up {rep.files} files ({rep.bytes / 1e6:.1f} MB) to {rep.folder}"
          + (f"; still being written, not in the backup: {', '.join(rep.in_progress)}" if rep.in_progress else ""))
    return 0


def _restore(args: argparse.Namespace) -> int:
    from station.backup import check_backup, restore

    if args.check:
        m = check_backup(args.src)
        print(f"{args.src}: a complete backup of {len(m['files'])} files made {m['created']}; every hash matches")
        return 0
    s = _settings(args.config)
    into = args.into or s.recordings_dir
    database = None if args.into is not None else s.database
    rep = restore(args.src, into, database)
    print(f"restored {rep.files} files ({rep.bytes / 1e6:.1f} MB) into {rep.folder}")
    return 0
