"""Reading recordings, complete or cut off by a crash (results beside them: ``stored``)."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from station.bounded import load_yaml
from station.errors import RecordingFormatError, StationError
from station.recording.writer import FORMAT_NAME, STEP_FIELDS, utc_now


@dataclass(frozen=True)
class Step:
    """A step of a stepped-sine run; record window [start_sample, end_sample)."""

    index: int
    crank_frequency_hz: float
    crank_radius_m: float
    start_sample: int
    end_sample: int
    lost_in_window: int = 0

    @property
    def usable(self) -> bool:
        """False when samples were lost inside the record window (never silently used)."""
        return self.lost_in_window == 0


@dataclass(frozen=True)
class Recording:
    """A run in memory, channels in physical units: displacement in m, force signal in V."""

    path: Path
    run_id: str
    transducer_id: str
    source: str
    sample_rate_hz: float
    displacement_m: np.ndarray
    force_V: np.ndarray
    steps: list[Step]
    load_mass_kg: float
    end_mass_kg: float | None
    sensitivity_V_per_N: float
    capacity_N: float
    config: dict[str, Any]
    lost_samples: np.ndarray  # (k, 2): first_sample, count
    exit_status: str  # completed, aborted, failed, interrupted
    reason: str
    complete: bool
    start_time: str
    end_time: str
    software_version: str
    documents: list[dict[str, Any]] = field(default_factory=list)
    attrs: dict[str, Any] = field(default_factory=dict)

    def step_signals(self, step: Step) -> tuple[np.ndarray, np.ndarray]:
        """(displacement_m, force_V) of one step's record window."""
        sl = slice(step.start_sample, step.end_sample)
        return self.displacement_m[sl], self.force_V[sl]


def open_recording(path: Path) -> tuple[h5py.File, bool]:
    """Open a recording read-only (a file cut off by a crash in SWMR-read mode): (the h5py file, whether it
    opened cleanly); RecordingFormatError when it is missing or not HDF5.  The caller closes the file."""
    if not path.exists():
        raise RecordingFormatError(f"{path}: no such recording")
    try:
        return h5py.File(path, "r"), True
    except OSError as first:
        try:
            return h5py.File(path, "r", swmr=True), False
        except OSError:
            raise RecordingFormatError(f"{path}: not a readable HDF5 recording ({first})") from None


def _attr(f: h5py.File, name: str, path: Path) -> Any:
    if name not in f.attrs:
        raise RecordingFormatError(f"{path}: attribute {name!r} expected in the root group, not found")
    v = f.attrs[name]
    return v.item() if isinstance(v, np.generic) else v


def _channel(f: h5py.File, name: str, path: Path) -> np.ndarray:
    key = f"raw/{name}"
    if key not in f:
        raise RecordingFormatError(f"{path}: dataset /{key} expected, not found")
    d = f[key]
    for a in ("scale", "offset", "physical_unit"):
        if a not in d.attrs:
            raise RecordingFormatError(f"{path}: /{key} lacks its {a!r} attribute")
    return d[...].astype(np.float64) * float(d.attrs["scale"]) + float(d.attrs["offset"])


def read_recording(path: str | Path) -> Recording:
    """Load a recording; raises RecordingFormatError naming what is missing or malformed."""
    p = Path(path)
    f, clean = open_recording(p)
    with f:
        if f.attrs.get("format") != FORMAT_NAME:
            raise RecordingFormatError(f"{p}: format {FORMAT_NAME!r} expected, got {f.attrs.get('format')!r}")
        disp, force = _channel(f, "displacement", p), _channel(f, "force", p)
        n = min(disp.size, force.size)  # a crash can cut one channel one chunk shorter
        disp, force = disp[:n], force[:n]
        cols = {k: f[f"steps/{k}"][...] for k in STEP_FIELDS if f"steps/{k}" in f}
        k_steps = min((len(v) for v in cols.values()), default=0)
        steps = [Step(index=i, crank_frequency_hz=float(cols["crank_frequency_hz"][i]),
                      crank_radius_m=float(cols["crank_radius_m"][i]),
                      start_sample=int(cols["start_sample"][i]), end_sample=int(cols["end_sample"][i]),
                      lost_in_window=int(cols.get("lost_in_window", np.zeros(k_steps))[i]))
                 for i in range(k_steps) if int(cols["end_sample"][i]) <= n]
        docs_raw = bytes(f["documents"][...]) if "documents" in f else b""
        documents = _parse_documents(docs_raw)
        config_text = bytes(f["config/yaml"][...]).decode() if "config/yaml" in f else ""
        status = str(_attr(f, "exit_status", p))
        end_mass = float(_attr(f, "end_mass_kg", p))
        complete = clean and status != "running" and not p.name.endswith(".partial")
        attrs = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in f.attrs.items()}
        return Recording(
            path=p, run_id=str(_attr(f, "run_id", p)), transducer_id=str(_attr(f, "transducer_id", p)),
            source=str(attrs.get("source", "")), sample_rate_hz=float(_attr(f, "sample_rate_hz", p)),
            displacement_m=disp, force_V=force, steps=steps,
            load_mass_kg=float(_attr(f, "load_mass_kg", p)),
            end_mass_kg=None if math.isnan(end_mass) else end_mass,
            sensitivity_V_per_N=float(_attr(f, "sensitivity_V_per_N", p)),
            capacity_N=float(_attr(f, "capacity_N", p)),
            config=(load_yaml(config_text, f"{p}: config/yaml", RecordingFormatError) or {}) if config_text else {},
            lost_samples=f["lost_samples"][...] if "lost_samples" in f else np.zeros((0, 2), dtype=np.int64),
            exit_status=status if complete else "interrupted",
            reason=str(attrs.get("reason", "")) if complete else "recording was cut off before its stop record",
            complete=complete, start_time=str(attrs.get("start_time", "")),
            end_time=str(attrs.get("end_time", "")), software_version=str(attrs.get("software_version", "")),
            documents=documents, attrs=attrs,
        )


def read_documents(path: str | Path) -> list[dict[str, Any]]:
    """The recording's documents (start, descriptors, stop) without loading its samples."""
    f, _ = open_recording(Path(path))
    with f:
        return _parse_documents(bytes(f["documents"][...]) if "documents" in f else b"")


def start_metadata(documents: list[dict[str, Any]]) -> dict[str, Any]:
    """The start document's ``metadata`` ({} when there is none)."""
    start = next((d for d in documents if d.get("kind") == "start"), {})
    meta = start.get("metadata")
    return meta if isinstance(meta, dict) else {}


def _parse_documents(raw: bytes) -> list[dict[str, Any]]:
    """JSON-lines documents; a last line cut off by a crash is dropped."""
    out = []
    for line in raw.decode(errors="replace").splitlines():
        try:
            doc = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(doc, dict):
            out.append(doc)
    return out


def recover_partial(path: str | Path) -> Path:
    """Turn a ``*.h5.partial`` left by a crash into a complete ``*.h5`` marked interrupted.

    The readable content is copied into a new file; the partial file is removed only after the copy
    has been read back.  Returns the new path.
    """
    src = Path(path)
    if not src.name.endswith(".h5.partial"):
        raise StationError(f"{src}: only *.h5.partial files are recovered")
    dst = src.with_name(src.name[: -len(".partial")])
    if dst.exists():
        raise StationError(f"{dst} exists already; not overwriting it")
    f, _ = open_recording(src)
    tmp = dst.with_name(dst.name + ".recovering")
    with f, h5py.File(tmp, "w") as out:
        for key in f:
            f.copy(f[key], out, name=key)
        n = min(out["raw/displacement"].shape[0], out["raw/force"].shape[0])
        for ch in ("displacement", "force"):
            out[f"raw/{ch}"].resize((n,))
        out.attrs.update({k: v for k, v in f.attrs.items()})
        out.attrs.update({"exit_status": "interrupted", "end_time": utc_now(),
                          "reason": "process stopped before the run ended; recovered from partial file"})
    read_recording(tmp)  # must read back before the partial file goes
    os.replace(tmp, dst)
    src.unlink()
    return dst
