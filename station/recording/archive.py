"""A recording with everything derived from it as one ZIP archive: the HDF5 recording, the results
stored beside it (``<run>.results/``), the certificates issued for it (``certificates/``), and
``MANIFEST.json`` with each file's SHA-256 and size (what to check after a transfer)."""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path
from typing import Any

from station import __version__
from station.recording.stored import TMP_MARK, sidecar_dir

CERTIFICATES = "certificates"


def archive_files(recording: Path) -> list[tuple[str, Path]]:
    """(name in the archive, file) of a recording, its stored results and its certificates."""
    recording = Path(recording)
    out = [(recording.name, recording)]
    side = sidecar_dir(recording)
    if side.is_dir():
        out += [(f"{side.name}/{p.relative_to(side).as_posix()}", p) for p in sorted(side.rglob("*"))
                if p.is_file() and TMP_MARK not in p.name]
    certs = recording.parent / CERTIFICATES
    if certs.is_dir():
        for rec in sorted(certs.glob("*.json")):
            try:
                doc = json.loads(rec.read_bytes())
            except ValueError:
                continue
            if doc.get("recording") != recording.name:
                continue
            number = str(doc.get("number", rec.stem))
            out += [(f"{CERTIFICATES}/{p.name}", p) for p in sorted(certs.glob(f"{number}.*")) if p.is_file()]
    return out


def recording_archive(recording: Path) -> bytes:
    """The ZIP archive of the recording (module docstring)."""
    files: dict[str, dict[str, Any]] = {}
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as z:
        for name, path in archive_files(recording):
            data = path.read_bytes()
            z.writestr(name, data)
            files[name] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
        manifest = {"format": "sinecal-recording-archive", "version": 1, "software": __version__,
                    "recording": Path(recording).name, "files": files}
        z.writestr("MANIFEST.json", json.dumps(manifest, indent=1, sort_keys=True))
    return buf.getvalue()
