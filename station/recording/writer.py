"""Crash-safe HDF5 recording writer (layout: docs/recording-format.md).

A run is written to ``<name>.h5.partial`` in HDF5 SWMR mode: raw samples are appended in chunks
and flushed at least every ``flush_interval_s``; a process killed at any moment leaves a file that
opens (read-only, SWMR) with every flushed sample.  ``finish`` writes the stop document and exit
status and renames the file to ``<name>.h5``.  Nothing is ever overwritten: an existing target
name is refused.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import shutil
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from station import __version__
from station.errors import StationError

log = logging.getLogger(__name__)

FORMAT_NAME = "sinecal-recording"
FORMAT_VERSION = 1
EXIT_STATUSES = ("completed", "aborted", "failed", "interrupted")
STEP_FIELDS: dict[str, tuple[str, str]] = {  # name -> (dtype, unit)
    "crank_frequency_hz": ("f8", "Hz"),
    "crank_radius_m": ("f8", "m"),
    "start_sample": ("i8", "sample"),
    "end_sample": ("i8", "sample"),
    "lost_in_window": ("i8", "sample"),
}


@dataclass(frozen=True)
class ChannelSpec:
    """How a raw channel is stored: ``physical = stored * scale + offset`` in ``physical_unit``.

    dtype 'i2' for ADC codes (stored unit 'count'), 'f8' for samples already in physical units.
    """

    name: str
    dtype: str
    stored_unit: str
    physical_unit: str
    scale: float
    offset: float = 0.0
    volts_per_count: float | None = None


@dataclass(frozen=True)
class RunMetadata:
    """What a recording says about its run (root attributes).  Masses in kg, sensitivity in V/N of
    the recorded force signal (transducer x conditioner), capacity in N."""

    run_id: str
    transducer_id: str
    source: str  # "simulate", "calibrate" or "import"
    sample_rate_hz: float
    load_mass_kg: float
    end_mass_kg: float | None
    sensitivity_V_per_N: float
    capacity_N: float
    config_yaml: str
    # the DAQ bridge as it reported itself at connect (adc, resolution, channels, clock, link; see
    # drivers.daq.DaqHardware.as_attrs) and the sample rate asked of it (``sample_rate_hz`` is the
    # rate its ADC delivers)
    daq_hardware: Mapping[str, str | float | int] | None = None
    sample_rate_requested_hz: float | None = None
    drive_profile_yaml: str | None = None  # the motor drive's profile (docs/drive-profiles.md), verbatim
    # temperature and humidity during the run (station.environment.run_environment), in the start document
    environment: Mapping[str, Any] | None = None


def new_run_id(transducer_id: str) -> str:
    """A unique, sortable run id: <UTC timestamp>-<transducer id>-<random suffix>."""
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S")
    return f"{stamp}-{transducer_id}-{os.urandom(3).hex()}"


def utc_now() -> str:
    """Current time, ISO 8601 with time zone."""
    return datetime.now(UTC).isoformat(timespec="milliseconds")


class DiskFullError(StationError):
    """The recordings folder has less free space than the reserve: nothing more is written.

    The writer refuses *before* the disk is full because HDF5 cannot recover from a failed write
    (the library may crash when the file is closed); what was flushed stays readable."""


class RecordingWriter:
    """Appends raw samples, steps, lost-sample reports and run documents to a partial file.

    ``min_free_bytes``: free space kept in reserve on the recordings' file system; an append that
    would eat into it raises DiskFullError (checked at least twice a second).
    """

    def __init__(self, out_dir: str | Path, meta: RunMetadata, channels: tuple[ChannelSpec, ChannelSpec],
                 *, plan: dict[str, Any] | None = None, flush_interval_s: float = 0.5,
                 chunk_samples: int = 20_000, min_free_bytes: int = 64 * 2**20) -> None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        self.final_path = out / f"{meta.run_id}.h5"
        self.partial_path = out / f"{meta.run_id}.h5.partial"
        for p in (self.final_path, self.partial_path):
            if p.exists():
                raise StationError(f"refusing to overwrite existing recording {p}")
        self.meta = meta
        self._min_free = min_free_bytes
        self._free_checked = 0.0
        self._free = 0
        self._dir = out
        self._check_space(0)
        self._flush_interval = flush_interval_s
        self._last_flush = time.monotonic()
        self._n = 0
        # a small chunk cache: appends only ever touch the last chunk of each channel
        f = h5py.File(self.partial_path, "w-", libver="latest", rdcc_nbytes=8 * chunk_samples * 8)
        self._f = f
        f.attrs.update({
            "format": FORMAT_NAME, "format_version": FORMAT_VERSION, "run_id": meta.run_id,
            "transducer_id": meta.transducer_id, "source": meta.source, "start_time": utc_now(),
            "software_version": __version__, "sample_rate_hz": meta.sample_rate_hz,
            "load_mass_kg": meta.load_mass_kg,
            "end_mass_kg": np.nan if meta.end_mass_kg is None else meta.end_mass_kg,
            "sensitivity_V_per_N": meta.sensitivity_V_per_N, "capacity_N": meta.capacity_N,
            "exit_status": "running", "end_time": "", "reason": "",
        })
        f.create_dataset("config/yaml", data=np.frombuffer(meta.config_yaml.encode(), dtype=np.uint8))
        f["config"].attrs["encoding"] = "utf-8 YAML"
        if meta.drive_profile_yaml is not None:
            f.create_dataset("config/drive_profile",
                             data=np.frombuffer(meta.drive_profile_yaml.encode(), dtype=np.uint8))
        raw = f.create_group("raw")
        raw.attrs.update({"sample_rate_hz": meta.sample_rate_hz, "units_of_time": "s"})
        if meta.sample_rate_requested_hz is not None:
            raw.attrs["sample_rate_requested_hz"] = meta.sample_rate_requested_hz
        if meta.daq_hardware is not None:
            raw.attrs.update(dict(meta.daq_hardware))
        self._raw = []
        for ch in channels:
            d = raw.create_dataset(ch.name, shape=(0,), maxshape=(None,), dtype=ch.dtype,
                                   chunks=(chunk_samples,))
            d.attrs.update({"stored_unit": ch.stored_unit, "physical_unit": ch.physical_unit,
                            "scale": ch.scale, "offset": ch.offset})
            if ch.volts_per_count is not None:
                d.attrs["volts_per_count"] = ch.volts_per_count
            self._raw.append(d)
        steps = f.create_group("steps")
        self._steps = {}
        for name, (dtype, unit) in STEP_FIELDS.items():
            d = steps.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(64,))
            d.attrs["unit"] = unit
            self._steps[name] = d
        self._lost = f.create_dataset("lost_samples", shape=(0, 2), maxshape=(None, 2), dtype="i8",
                                      chunks=(256, 2))
        self._lost.attrs["columns"] = "first_sample, count"
        self._docs = f.create_dataset("documents", shape=(0,), maxshape=(None,), dtype="u1",
                                      chunks=(4096,))
        self._docs.attrs["encoding"] = "JSON lines (utf-8): start, step..., stop documents"
        f.create_group("processed")
        f.create_group("results")
        f.swmr_mode = True
        self._closed = False
        self.document("start", {"run_id": meta.run_id, "time": f.attrs["start_time"], "plan": plan or {},
                                "metadata": {k: v for k, v in asdict(meta).items()
                                             if k not in ("config_yaml", "drive_profile_yaml")},
                                "software_version": __version__})

    @property
    def samples_written(self) -> int:
        return self._n

    def append(self, displacement: np.ndarray, force: np.ndarray) -> None:
        """Append one block of both channels (equal length, stored dtype)."""
        if displacement.shape != force.shape or displacement.ndim != 1:
            raise ValueError(f"channels must be equal 1-D blocks, got {displacement.shape} and {force.shape}")
        n0, n = self._n, displacement.size
        self._check_space(n * (displacement.itemsize + force.itemsize))
        for d, block in zip(self._raw, (displacement, force), strict=True):
            d.resize((n0 + n,))
            d[n0:] = block
        self._n = n0 + n
        self._maybe_flush()

    def _check_space(self, nbytes: int) -> None:
        now = time.monotonic()
        if now - self._free_checked > 0.5 or self._free - nbytes < 2 * self._min_free:
            self._free = shutil.disk_usage(self._dir).free
            self._free_checked = now
        if self._free - nbytes < self._min_free:
            raise DiskFullError(f"disk nearly full: {self._free / 2**20:.1f} MiB free in {self._dir}, "
                                f"{self._min_free / 2**20:.1f} MiB kept in reserve; recording stopped")
        self._free -= nbytes

    def add_step(self, *, crank_frequency_hz: float, crank_radius_m: float, start_sample: int,
                 end_sample: int, lost_in_window: int = 0, extra: dict[str, Any] | None = None) -> None:
        """Record one step's record window [start_sample, end_sample) and its step document."""
        values = {"crank_frequency_hz": crank_frequency_hz, "crank_radius_m": crank_radius_m,
                  "start_sample": start_sample, "end_sample": end_sample, "lost_in_window": lost_in_window}
        for name, d in self._steps.items():
            k = d.shape[0]
            d.resize((k + 1,))
            d[k] = values[name]
        units = {k: u for k, (_, u) in STEP_FIELDS.items()}
        self.document("step", {"index": self._steps["start_sample"].shape[0] - 1, **values,
                               "units": units, **(extra or {})})

    def add_lost(self, first_sample: int, count: int) -> None:
        """Report ``count`` samples missing from index ``first_sample`` on (raw data has no gap:
        acquisition fills the missing positions, see the format document)."""
        k = self._lost.shape[0]
        self._lost.resize((k + 1, 2))
        self._lost[k] = (first_sample, count)
        self._maybe_flush()

    def document(self, kind: str, body: dict[str, Any]) -> None:
        """Append one run document (JSON line) of kind start, step, event or stop."""
        line = (json.dumps({"kind": kind, **body}, default=jsonable) + "\n").encode()
        k = self._docs.shape[0]
        self._docs.resize((k + len(line),))
        self._docs[k:] = np.frombuffer(line, dtype=np.uint8)
        self.flush()

    def _maybe_flush(self) -> None:
        if time.monotonic() - self._last_flush >= self._flush_interval:
            self.flush()

    def flush(self) -> None:
        """Make everything appended so far durable and visible to readers."""
        self._f.flush()
        self._last_flush = time.monotonic()

    def finish(self, exit_status: str, reason: str = "") -> Path:
        """Write the stop document, close, set the exit status and move the file into place."""
        if exit_status not in EXIT_STATUSES:
            raise ValueError(f"exit status must be one of {EXIT_STATUSES}, got {exit_status!r}")
        end = utc_now()
        self.document("stop", {"time": end, "exit_status": exit_status, "reason": reason,
                               "samples": self._n})
        self._f.close()
        self._closed = True
        with h5py.File(self.partial_path, "r+") as f:
            f.attrs.update({"exit_status": exit_status, "end_time": end, "reason": reason})
        os.replace(self.partial_path, self.final_path)
        log.info("recording %s closed: %s, %d samples", self.final_path, exit_status, self._n)
        return self.final_path

    def abandon(self) -> None:
        """Close without a stop document (the file stays *.partial and reads as interrupted).  Never
        raises: a file HDF5 cannot close (e.g. after a full disk) is closed at the descriptor."""
        if self._closed:
            return
        self._closed = True
        try:
            self._f.close()
        except Exception as exc:
            log.error("closing %s failed: %s", self.partial_path, exc)
            try:
                self._f.id.close()
            except Exception as exc2:
                log.error("closing the HDF5 file id of %s failed: %s", self.partial_path, exc2)


def is_disk_full(exc: BaseException | None) -> bool:
    """A write failed for lack of space: OSError ENOSPC/EDQUOT, or HDF5's RuntimeError quoting it
    (h5py does not keep the errno), also as the cause of another error."""
    seen = 0
    while exc is not None and seen < 8:
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if "No space left on device" in str(exc) or "Disk quota exceeded" in str(exc):
            return True
        exc, seen = exc.__cause__ or exc.__context__, seen + 1
    return False


def jsonable(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
