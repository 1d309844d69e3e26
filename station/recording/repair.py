"""Recordings damaged by an older station, repaired or named.

Earlier versions wrote results into the finished recording in place.  A kill or a full disk during
such a write left the HDF5 superblock's file-consistency flags set ("open for writing": plain
``h5py.File(path, "r")`` and even SWMR readers then fail with "file is already open for write") or
the file unreadable.  ``check_folder`` finds such files among a folder's ``*.h5`` and repairs each one
it can as ``h5clear -s`` does: the flags byte of the superblock (version 2 or 3, the format the
writer uses) is cleared and the superblock's checksum (Jenkins' lookup3, as HDF5 computes it)
rewritten, fsync'ed; then every dataset is read back and the recording read as a whole.  A file that
still does not read gets its original superblock back and is named (logged, listed in ``/health``),
never deleted.  ``check_folder`` also removes the temporary files of result writes that a kill
interrupted (``stored.stale_temporaries``).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py

from station.recording.reader import read_recording
from station.recording.stored import stale_temporaries

log = logging.getLogger(__name__)
SIGNATURE = b"\x89HDF\r\n\x1a\n"
FLAGS_OFFSET = 11  # signature (8), version, size of offsets, size of lengths, then the flags byte
_M = 0xFFFFFFFF


@dataclass(frozen=True)
class FolderCheck:
    """What ``check_folder`` found: recordings repaired (file names), recordings that cannot be
    read (file name and why), temporary files of interrupted result writes removed."""

    repaired: tuple[str, ...] = ()
    unreadable: tuple[tuple[str, str], ...] = ()
    temporaries_removed: tuple[str, ...] = ()
    notes: tuple[str, ...] = field(default_factory=tuple)

    def to_dict(self) -> dict[str, Any]:
        return {"repaired": list(self.repaired),
                "unreadable": [{"file": n, "error": e} for n, e in self.unreadable],
                "temporaries_removed": list(self.temporaries_removed), "notes": list(self.notes)}


def _rot(x: int, k: int) -> int:
    return ((x << k) | (x >> (32 - k))) & _M


def lookup3(data: bytes, initval: int = 0) -> int:
    """Bob Jenkins' lookup3 ``hashlittle``: the checksum of HDF5's version 2/3 superblock."""
    n = len(data)
    a = b = c = (0xDEADBEEF + n + initval) & _M
    i = 0

    def word(j: int) -> int:
        return int.from_bytes(data[j:j + 4], "little")

    while n > 12:
        a, b, c = (a + word(i)) & _M, (b + word(i + 4)) & _M, (c + word(i + 8)) & _M
        a = (a - c) & _M ^ _rot(c, 4)
        c = (c + b) & _M
        b = (b - a) & _M ^ _rot(a, 6)
        a = (a + c) & _M
        c = (c - b) & _M ^ _rot(b, 8)
        b = (b + a) & _M
        a = (a - c) & _M ^ _rot(c, 16)
        c = (c + b) & _M
        b = (b - a) & _M ^ _rot(a, 19)
        a = (a + c) & _M
        c = (c - b) & _M ^ _rot(b, 4)
        b = (b + a) & _M
        i, n = i + 12, n - 12
    if n == 0:
        return c
    data = data[i:] + b"\0" * (12 - n)
    i = 0
    a, b, c = (a + word(0)) & _M, (b + word(4)) & _M, (c + word(8)) & _M
    c = (c ^ b) - _rot(b, 14) & _M
    a = (a ^ c) - _rot(c, 11) & _M
    b = (b ^ a) - _rot(a, 25) & _M
    c = (c ^ b) - _rot(b, 16) & _M
    a = (a ^ c) - _rot(c, 4) & _M
    b = (b ^ a) - _rot(a, 14) & _M
    c = (c ^ b) - _rot(b, 24) & _M
    return c


def _superblock(path: Path) -> tuple[bytes, int]:
    """(the version 2/3 superblock at the start of the file, its length without the checksum)."""
    with open(path, "rb") as fh:
        head = fh.read(12)
        if head[:8] != SIGNATURE or len(head) < 12 or head[8] not in (2, 3):
            raise OSError("no version 2/3 HDF5 superblock at the start of the file")
        n = 12 + 4 * head[9]
        sb = head + fh.read(n + 4 - 12)
    if len(sb) != n + 4 or lookup3(sb[:n]) != int.from_bytes(sb[n:], "little"):
        raise OSError("HDF5 superblock checksum does not match")
    return sb, n


def _write_superblock(path: Path, sb: bytes) -> None:
    with open(path, "r+b") as fh:
        fh.write(sb)
        fh.flush()
        os.fsync(fh.fileno())


def clear_write_flag(path: Path) -> bytes | None:
    """Clear the superblock's consistency flags (``h5clear -s``); returns the original superblock
    (to put back) or None when no flag was set."""
    sb, n = _superblock(path)
    if sb[FLAGS_OFFSET] == 0:
        return None
    new = bytearray(sb[:n])
    new[FLAGS_OFFSET] = 0
    _write_superblock(path, bytes(new) + lookup3(bytes(new)).to_bytes(4, "little"))
    return sb


def verify(path: Path) -> None:
    """Read every dataset of the file, then the recording as a whole; raises what fails."""
    with h5py.File(path, "r") as f:
        def read(name: str, obj: Any) -> None:
            if isinstance(obj, h5py.Dataset):
                obj[...]
        f.visititems(read)
    read_recording(path)


def repair_recording(path: Path) -> None:
    """Clear the write flag left by an interrupted write and verify the whole file; on failure the
    original superblock is put back and the error raised."""
    original = clear_write_flag(path)
    try:
        verify(path)
    except Exception:
        if original is not None:
            _write_superblock(path, original)
        raise


def _opens_cleanly(path: Path) -> bool:
    try:
        with h5py.File(path, "r"):
            return True
    except OSError:
        return False


def check_folder(folder: Path) -> FolderCheck:
    """Repair or name the damaged ``*.h5`` recordings of ``folder``; remove interrupted result
    writes.  Never raises for a bad file: it is listed in ``unreadable`` and logged by name."""
    repaired: list[str] = []
    unreadable: list[tuple[str, str]] = []
    notes: list[str] = []
    removed: list[str] = []
    if not folder.is_dir():
        return FolderCheck()
    for q in stale_temporaries(folder):
        q.unlink(missing_ok=True)
        removed.append(f"{q.parent.name}/{q.name}")
    for p in sorted(folder.glob("*.h5")):
        if not p.is_file() or _opens_cleanly(p):
            continue
        try:
            repair_recording(p)
        except Exception as exc:  # any damage: name the file, go on with the others
            msg = f"{p}: recording cannot be read and was not repaired ({exc}); it is left as it is"
            log.error("%s", msg)
            unreadable.append((p.name, str(exc)))
            continue
        repaired.append(p.name)
        log.warning("%s: the write flag left by an interrupted write was cleared; every dataset reads", p)
    return FolderCheck(tuple(repaired), tuple(unreadable), tuple(removed), tuple(notes))
