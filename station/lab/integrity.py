"""A recording is the one that was measured: its SHA-256, taken when it was closed, stored with the
run, and checked before the recording is read for a report or a certificate."""

from __future__ import annotations

import hashlib
from pathlib import Path

from station.errors import StationError

CHUNK = 1 << 20


class RecordingTamperedError(StationError):
    """The recording's content is not what was closed (or its hash was never stored)."""


def sha256_file(path: Path) -> str:
    """SHA-256 of a file's bytes (hex), read in 1 MiB pieces."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK):
            h.update(chunk)
    return h.hexdigest()


def check_recording(path: Path, expected: str | None, *, required: bool = False) -> str:
    """The recording's SHA-256 if it equals ``expected``; RecordingTamperedError naming the file
    otherwise.  ``expected`` None (a run recorded before hashes were stored) passes unless
    ``required`` (a certificate requires it)."""
    actual = sha256_file(path)
    if expected is None:
        if required:
            raise RecordingTamperedError(f"{path.name}: no SHA-256 was stored when the recording was closed; "
                                         "it cannot be shown to be the one measured")
        return actual
    if actual != expected:
        raise RecordingTamperedError(f"{path.name}: the recording was changed after it was closed (SHA-256 "
                                     f"{actual[:16]}... instead of {expected[:16]}...); refused")
    return actual
