"""Measured signals in and compensated signals out: CSV (a time column or a stated sample rate), an
HDF5 dataset, ``.npy``; written as CSV or HDF5 (time, estimate, u with their units).

Bounded: a file above ``MAX_SIGNAL_BYTES`` or a signal above ``MAX_SAMPLES`` is refused before it is
read; a time column must be uniform; a stated sample rate must agree with the time column and with
the filter's.  Every refusal is one ``BadInputError`` with what to do.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from station.errors import BadInputError

FloatArray = NDArray[np.float64]

MAX_SIGNAL_BYTES = 512 * 1024 * 1024
MAX_SAMPLES = 50_000_000
RATE_REL_TOL = 1e-6


@dataclass(frozen=True)
class Signal:
    """A uniformly sampled signal: values x (n,), sample rate in Hz, time of the first sample in s."""

    x: FloatArray
    sample_rate_hz: float
    t0_s: float = 0.0

    @property
    def time_s(self) -> FloatArray:
        return self.t0_s + np.arange(self.x.size) / self.sample_rate_hz


def _check_size(path: Path, max_bytes: int) -> None:
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise BadInputError(f"{path}: cannot read the signal ({exc.strerror})") from None
    if size > max_bytes:
        raise BadInputError(f"{path}: {size} bytes, above the limit of {max_bytes} bytes: split the signal")


def _rate(stated: float | None, found: float | None, path: Path) -> float:
    if found is not None and stated is not None and abs(found / stated - 1) > 1e-3:
        raise BadInputError(f"{path}: the time column gives {found:g} Hz, the stated sample rate is {stated:g} Hz")
    fs = stated if stated is not None else found
    if fs is None:
        raise BadInputError(f"{path}: no time column and no sample rate: state --sample-rate")
    if not (math.isfinite(fs) and fs > 0):
        raise BadInputError(f"{path}: sample rate {fs!r} Hz: it must be > 0")
    return float(fs)


def read_signal(path: str | Path, sample_rate_hz: float | None = None, dataset: str | None = None,
                column: str | None = None, max_bytes: int = MAX_SIGNAL_BYTES) -> Signal:
    """The signal in ``path`` (.csv, .h5/.hdf5 with ``dataset``, .npy)."""
    p = Path(path)
    _check_size(p, max_bytes)
    suffix = p.suffix.lower()
    t0, found = 0.0, None
    if suffix == ".npy":
        try:
            arr = np.load(p, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise BadInputError(f"{p}: not a readable .npy array ({exc})") from None
        x = np.asarray(arr, dtype=float).ravel() if arr.ndim == 1 or min(arr.shape) == 1 else None
        if x is None:
            raise BadInputError(f"{p}: an array of shape {arr.shape}: give one signal (1-D)")
    elif suffix in (".h5", ".hdf5"):
        import h5py

        try:
            with h5py.File(p, "r") as f:
                if dataset is None:
                    names: list[str] = []
                    f.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) and o.ndim == 1 else None)
                    if len(names) != 1:
                        raise BadInputError(f"{p}: {len(names)} one-dimensional datasets: name one with --dataset")
                    dataset = names[0]
                if dataset not in f or not isinstance(f[dataset], h5py.Dataset) or f[dataset].ndim != 1:
                    raise BadInputError(f"{p}: no one-dimensional dataset {dataset!r}")
                ds = f[dataset]
                if ds.size > MAX_SAMPLES:
                    raise BadInputError(f"{p}: {ds.size} samples, above the limit of {MAX_SAMPLES}")
                x = np.asarray(ds[()], dtype=float)
                rate = ds.attrs.get("sample_rate_hz", f.attrs.get("sample_rate_hz"))
                found = None if rate is None else float(rate)
        except OSError as exc:
            raise BadInputError(f"{p}: not a readable HDF5 file ({exc})") from None
    elif suffix == ".csv":
        x, tcol = _read_csv(p, column)
        if tcol is not None:
            if tcol.size < 2:
                raise BadInputError(f"{p}: fewer than 2 samples")
            dt = np.diff(tcol)
            step = float(np.median(dt))
            if not (step > 0) or np.max(np.abs(dt - step)) > 1e-3 * step:
                raise BadInputError(f"{p}: the time column is not uniformly sampled (steps from {dt.min():g} to "
                                    f"{dt.max():g} s): resample it first")
            found, t0 = (tcol.size - 1) / float(tcol[-1] - tcol[0]), float(tcol[0])
    else:
        raise BadInputError(f"{p}: unknown signal format {suffix!r}: give .csv, .h5/.hdf5 or .npy")
    if x.size > MAX_SAMPLES:
        raise BadInputError(f"{p}: {x.size} samples, above the limit of {MAX_SAMPLES}")
    if x.size == 0:
        raise BadInputError(f"{p}: the signal is empty")
    bad = ~np.isfinite(x)
    if bad.any():
        raise BadInputError(f"{p}: {int(bad.sum())} samples are NaN or infinite (the first at sample "
                            f"{int(np.flatnonzero(bad)[0])}): nothing was compensated; mend or cut the signal")
    return Signal(np.ascontiguousarray(x, dtype=float), _rate(sample_rate_hz, found, p), t0)


def _read_csv(p: Path, column: str | None) -> tuple[FloatArray, FloatArray | None]:
    """Values and time column (or None) of a CSV with a header; a time column is named time_s or time."""
    try:
        with p.open(encoding="utf-8") as fh:
            header = fh.readline()
            while header.lstrip().startswith("#"):
                header = fh.readline()
            cols = [c.strip().lower() for c in header.strip().split(",")]
            data = np.loadtxt(fh, delimiter=",", ndmin=2, comments="#")
    except (OSError, UnicodeDecodeError) as exc:
        raise BadInputError(f"{p}: not a readable CSV ({exc})") from None
    except ValueError as exc:
        raise BadInputError(f"{p}: a row is not a list of numbers ({exc})") from None
    if data.shape[1] != len(cols):
        raise BadInputError(f"{p}: {data.shape[1]} columns, the header names {len(cols)}")
    tname = next((c for c in ("time_s", "time") if c in cols), None)
    values = [c for c in cols if c != tname]
    if column is not None:
        if column.lower() not in values:
            raise BadInputError(f"{p}: no column {column!r} (columns: {', '.join(cols)})")
        vname = column.lower()
    elif len(values) == 1:
        vname = values[0]
    else:
        raise BadInputError(f"{p}: {len(values)} value columns ({', '.join(values)}): name one with --column")
    return data[:, cols.index(vname)], None if tname is None else data[:, cols.index(tname)]


def check_rate(signal_rate_hz: float, filter_rate_hz: float) -> None:
    """Refuse a signal whose sample rate is not the filter's."""
    if abs(signal_rate_hz / filter_rate_hz - 1) > RATE_REL_TOL:
        raise BadInputError(f"the signal is sampled at {signal_rate_hz:g} Hz, the filter was designed for "
                            f"{filter_rate_hz:g} Hz: design a filter for {signal_rate_hz:g} Hz")


def write_output(path: str | Path, time_s: FloatArray, estimate: FloatArray, u: FloatArray, unit: str,
                 attrs: dict[str, object]) -> Path:
    """CSV (time_s, estimate_<unit>, u_<unit>; '#' lines with attrs) or HDF5 (datasets with a unit)."""
    p = Path(path)
    if p.suffix.lower() in (".h5", ".hdf5"):
        import h5py

        with h5py.File(p, "w") as f:
            for name, arr, un in (("time", time_s, "s"), ("estimate", estimate, unit), ("u", u, unit)):
                d = f.create_dataset(name, data=arr)
                d.attrs["unit"] = un
            for k, v in attrs.items():
                f.attrs[k] = v if isinstance(v, (int, float, str)) else str(v)
        return p
    head = "".join(f"# {k}: {v}\n" for k, v in attrs.items())
    np.savetxt(p, np.column_stack([time_s, estimate, u]), delimiter=",", fmt="%.10g",
               header=head + f"time_s,estimate_{unit},u_{unit}", comments="")
    return p
