"""What analyses stored in a recording, read back: the one reader of ``/results`` and ``/processed``.

``write_results`` (``station.recording.reader``) stores a JSON document and optional arrays under
``/<group>/<name>``; the daemon's results endpoint, the report and the CLI read them here, never by
opening the HDF5 file themselves.  ``/processed/steps`` holds H(f) per step (arrays
``frequency_hz`` in Hz, ``H`` complex in V/(m/s^2), ``H_cov`` (n, 2, 2) covariance of Re H, Im H).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from station.recording.reader import _open


@dataclass(frozen=True)
class Stored:
    """One stored document: its name, when it was written (UTC ISO 8601), the JSON and its arrays."""

    name: str
    written: str
    doc: dict[str, Any]
    arrays: dict[str, np.ndarray] = field(default_factory=dict)


def _read(g: Any, name: str) -> Stored | None:
    if "json" not in g.attrs:
        return None
    arrays = {k: g[k][...] for k in g if hasattr(g[k], "shape")}
    return Stored(name, str(g.attrs.get("written", "")), json.loads(g.attrs["json"]), arrays)


def read_stored(path: str | Path, group: str = "results") -> dict[str, Stored]:
    """Every document of ``/<group>`` by name (empty if the group does not exist)."""
    f, _ = _open(Path(path))
    with f:
        if group not in f:
            return {}
        out = {}
        for name, g in f[group].items():
            s = _read(g, name)
            if s is not None:
                out[name] = s
        return out


def read_processed(path: str | Path) -> Stored | None:
    """``/processed/steps`` (H(f) of the steps the identification used) or None if not processed."""
    f, _ = _open(Path(path))
    with f:
        return _read(f["processed/steps"], "steps") if "processed/steps" in f else None
