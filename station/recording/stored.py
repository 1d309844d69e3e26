"""Results beside a closed recording: written atomically into its sidecar folder, read back.

A finished recording ``<run>.h5`` is never opened for writing again.  What is computed from it
(H(f) per step, identifications, campaigns, model-gap analyses) lives in the sidecar folder
``<run>.results/`` next to it, one HDF5 file per result, ``<group>.<name>.h5``:

* root attribute ``json``: the result as JSON; ``written``: ISO 8601 UTC time of writing;
  ``format`` ``"sinecal-result"``, ``format_version`` 1, ``group``, ``name``, ``recording`` (the
  recording's file name);
* one dataset per array given (e.g. ``frequency_hz``, ``H``, ``H_cov`` of ``processed.steps.h5``).

Each write goes to a temporary file in the same folder (``.<group>.<name>.h5.tmp-<pid>-<hex>``),
is fsync'ed, renamed over the result (``os.replace``) and the folder fsync'ed: a kill or a full disk
at any instant leaves the recording untouched and either the previous or the new result whole.
Recordings written before the sidecar existed hold results in their own ``/results`` and
``/processed`` groups: those are still read (a sidecar result of the same name wins) and never
written.  The daemon's results endpoint, the report and the CLI read results only here.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from station.errors import StationError
from station.recording.reader import open_recording
from station.recording.writer import jsonable, utc_now

log = logging.getLogger(__name__)
RESULT_FORMAT = "sinecal-result"
RESULT_FORMAT_VERSION = 1
GROUPS = ("results", "processed")
SIDECAR_SUFFIX = ".results"
TMP_MARK = ".tmp-"


class ResultWriteError(StationError):
    """A result could not be written (disk full, folder not writable): the previous result, if any,
    and the recording are unchanged."""


@dataclass(frozen=True)
class Stored:
    """One stored document: its name, when it was written (UTC ISO 8601), the JSON, its arrays and
    where it was read from (the sidecar file, or ``<recording>:/<group>/<name>`` for an old in-file
    result)."""

    name: str
    written: str
    doc: dict[str, Any]
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    source: str = ""


def sidecar_dir(recording: str | Path) -> Path:
    """The folder of a recording's results: ``<dir>/<run>.results`` for ``<dir>/<run>.h5``."""
    p = Path(recording)
    return p.with_name(p.name[: -len(".h5")] + SIDECAR_SUFFIX if p.name.endswith(".h5") else p.name + SIDECAR_SUFFIX)


def result_path(recording: str | Path, name: str, group: str = "results") -> Path:
    """Where ``write_result`` puts result ``name`` of ``group``."""
    return sidecar_dir(recording) / f"{group}.{name}.h5"


def _check(p: Path, name: str, group: str) -> None:
    if p.name.endswith(".partial"):
        raise StationError(f"{p}: results are written only for complete recordings")
    if not name or not name.replace("_", "").replace("-", "").replace("+", "").isalnum():
        raise ValueError(f"result name must be alphanumeric (with _ - +), got {name!r}")
    if group not in GROUPS:
        raise ValueError(f"results go into one of the groups {GROUPS}, got {group!r}")


def fsync_dir(folder: Path) -> None:
    """Make a rename or a new entry in ``folder`` durable."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_result(recording: str | Path, name: str, payload: dict[str, Any],
                 arrays: dict[str, np.ndarray] | None = None, *, group: str = "results",
                 keep_identical: bool = False) -> Path:
    """Store ``payload`` (JSON) and ``arrays`` as result ``name`` beside ``recording``, atomically,
    replacing an earlier result of that name.  The recording itself is not opened.  Returns the
    result's file; raises ResultWriteError (nothing changed) when it cannot be written.

    ``keep_identical`` (a result without arrays): an earlier result of the same document is kept
    as it is, not written again, so that what depends on its version (the report, a draft
    certificate) is not made again for nothing."""
    p = Path(recording)
    _check(p, name, group)
    if not p.is_file():
        raise StationError(f"{p}: no such recording")
    text = json.dumps(payload, default=jsonable)
    folder = sidecar_dir(p)
    final = folder / f"{group}.{name}.h5"
    if keep_identical and not arrays and _holds(final, text):
        return final
    tmp = folder / f".{final.name}{TMP_MARK}{os.getpid()}-{secrets.token_hex(3)}"
    try:
        if not folder.is_dir():
            folder.mkdir(exist_ok=True)
            fsync_dir(folder.parent)
        with h5py.File(tmp, "w") as f:
            f.attrs.update({"format": RESULT_FORMAT, "format_version": RESULT_FORMAT_VERSION, "group": group,
                            "name": name, "recording": p.name, "written": utc_now(), "json": text})
            for key, arr in (arrays or {}).items():
                f.create_dataset(key, data=arr)
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, final)
        fsync_dir(folder)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise ResultWriteError(f"{final}: result {group}/{name} not written ({exc.strerror or exc}); "
                               "the recording and any earlier result are unchanged") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return final


def _holds(final: Path, text: str) -> bool:
    """Whether the result file ``final`` exists, is of this format and holds the document ``text``
    and no arrays."""
    if not final.is_file():
        return False
    try:
        with h5py.File(final, "r") as f:
            return (f.attrs.get("format") == RESULT_FORMAT and f.attrs.get("format_version") == RESULT_FORMAT_VERSION
                    and f.attrs.get("json") == text and len(f) == 0)
    except (OSError, ValueError):
        return False


def _from_group(g: Any, name: str, source: str) -> Stored | None:
    if "json" not in g.attrs:
        return None
    arrays = {k: g[k][...] for k in g if hasattr(g[k], "shape")}
    return Stored(name, str(g.attrs.get("written", "")), json.loads(g.attrs["json"]), arrays, source)


def _sidecar_files(recording: Path, group: str) -> Iterator[tuple[str, Path]]:
    folder = sidecar_dir(recording)
    if not folder.is_dir():
        return
    for q in sorted(folder.glob(f"{group}.*.h5")):
        yield q.name[len(group) + 1: -len(".h5")], q


def read_stored(path: str | Path, group: str = "results") -> dict[str, Stored]:
    """Every result of ``group`` by name: the sidecar's, over those an old recording holds inside.
    A sidecar file that cannot be read is skipped with a log line (it is never half-written; this
    is a damaged disk or a foreign file)."""
    p = Path(path)
    out: dict[str, Stored] = {}
    f, _ = open_recording(p)
    with f:
        if group in f:
            for name, g in f[group].items():
                s = _from_group(g, name, f"{p.name}:/{group}/{name}")
                if s is not None:
                    out[name] = s
    for name, q in _sidecar_files(p, group):
        try:
            with h5py.File(q, "r") as rf:
                s = _from_group(rf, name, str(q))
        except (OSError, ValueError) as exc:
            log.warning("%s: result not readable, skipped (%s)", q, exc)
            continue
        if s is not None:
            out[name] = s
    return out


def read_one(path: str | Path, name: str, group: str = "results") -> Stored | None:
    """Result ``name`` of ``group`` (sidecar first, then an old in-file one), or None."""
    p = Path(path)
    q = result_path(p, name, group)
    if q.is_file():
        try:
            with h5py.File(q, "r") as rf:
                s = _from_group(rf, name, str(q))
            if s is not None:
                return s
        except (OSError, ValueError) as exc:
            log.warning("%s: result not readable (%s)", q, exc)
    f, _ = open_recording(p)
    with f:
        key = f"{group}/{name}"
        return _from_group(f[key], name, f"{p.name}:/{key}") if key in f else None


def read_result(path: str | Path, name: str, *, group: str = "results") -> dict[str, Any] | None:
    """The JSON document of result ``name``, or None."""
    s = read_one(path, name, group)
    return None if s is None else s.doc


def read_processed(path: str | Path) -> Stored | None:
    """``processed/steps`` (H(f) of the steps the identification used) or None if not processed:
    arrays ``frequency_hz`` in Hz, ``H`` complex in V/(m/s^2), ``H_cov`` (n, 2, 2) covariance of
    Re H, Im H."""
    return read_one(path, "steps", "processed")


def results_version(path: str | Path) -> tuple[tuple[str, int], ...]:
    """What changes when a result is written beside ``path`` (names and modification times of the
    sidecar's files): with the recording's own stat, the key of caches of what is shown."""
    folder = sidecar_dir(path)
    if not folder.is_dir():
        return ()
    out = []
    for q in sorted(folder.glob("*.h5")):
        try:
            out.append((q.name, q.stat().st_mtime_ns))
        except OSError:
            continue
    return tuple(out)


def stale_temporaries(recordings_dir: Path) -> list[Path]:
    """Temporary result files left by a writer that was killed (never read as results)."""
    return sorted(q for q in recordings_dir.glob(f"*{SIDECAR_SUFFIX}/.*{TMP_MARK}*") if q.is_file())
