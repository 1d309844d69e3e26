"""The sinecal-csv interchange format (docs/interchange-format.md): runs recorded on other DAQs.

``RUN.yaml`` + one CSV per step (header ``t_s,displacement_m,force_V``).  Version 2 (written by
export) gives each step its own crank radius and may state the rig's limits (``rig``), so that the
station's own plans export and a proposed follow-up run recorded elsewhere imports; version 1 (one
radius per run) is still read.  Import validates every file completely before anything is written; a
malformed file is refused with the file, the line and the reason, and no half-written recording is
left behind.
"""

from __future__ import annotations

import io
import logging
import os
import re
import shutil
import stat
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from station.bounded import MAX_YAML_BYTES, load_yaml, quote, read_text_limited
from station.config import CrankFrequencyHz, CrankRadiusM, MeasurementChain
from station.errors import RecordingFormatError, StationError
from station.recording import ChannelSpec, RecordingWriter, RunMetadata, new_run_id, read_recording

log = logging.getLogger(__name__)

HEADER = "t_s,displacement_m,force_V"
FORMAT = "sinecal-csv"
VERSIONS = (1, 2)
VERSION = 2  # what export writes
RATE_TOLERANCE = 1e-3  # allowed deviation of each time step from 1/fs, as a fraction of 1/fs
MAX_STEP_FILE_BYTES = 64 << 20  # one step file: ~1.6 million samples (80 s at 20 kHz) at ~40 bytes a line
MAX_RUN_BYTES = 256 << 20  # all the step files one RUN.yaml names, counted each time it names one


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class CsvTransducer(_Strict):
    id: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.\-]+$")
    capacity_N: float = Field(gt=0)
    sensitivity_V_per_N: float = Field(description="of the recorded force_V signal; either sign")


class CsvStep(_Strict):
    file: str = Field(min_length=1)
    crank_frequency_hz: CrankFrequencyHz
    crank_radius_m: CrankRadiusM | None = Field(default=None, description="v2: this step's radius")


class CsvRange(_Strict):
    min: float = Field(ge=0)
    max: float = Field(gt=0)


class CsvRig(_Strict):
    """v2: the limits of the rig the run was made on (what a follow-up run may use)."""

    crank_frequency_hz: CsvRange
    crank_radius_m: CsvRange
    peak_force_fraction: float = Field(default=0.8, gt=0, le=1.0, description="of the capacity")


class RunFile(_Strict):
    """RUN.yaml of the interchange format, versions 1 and 2 (``VERSIONS``)."""

    format: str
    format_version: int
    sample_rate_hz: float = Field(gt=0, le=1e6)
    crank_radius_m: float | None = Field(default=None, gt=0, le=1.0,
                                         description="v1: the run's radius; v2: the default of its steps")
    rig: CsvRig | None = None
    top_mass_kg: float = Field(gt=0, le=1000, description="load mass m_l incl. adaption")
    end_mass_kg: float | None = Field(default=None, gt=0, le=100)
    end_mass_std_kg: float | None = Field(default=None, ge=0, le=100, description="default 5 % of end_mass_kg")
    top_mass_std_kg: float | None = Field(default=None, ge=0, le=100, description="default 1e-4 of top_mass_kg")
    measurement_chain: MeasurementChain | None = None
    transducer: CsvTransducer
    steps: list[CsvStep] = Field(min_length=1)


def _load_run_file(path: Path) -> tuple[RunFile, str]:
    """RUN.yaml validated, and its text."""
    text = read_text_limited(path, MAX_YAML_BYTES, "RUN.yaml", RecordingFormatError)
    data = load_yaml(text, str(path), RecordingFormatError)
    if not isinstance(data, dict):
        raise RecordingFormatError(f"{path}: a mapping was expected, got {type(data).__name__}")
    if data.get("format") != FORMAT or data.get("format_version") not in VERSIONS:
        raise RecordingFormatError(f"{path}: format {FORMAT!r} version {' or '.join(map(str, VERSIONS))} expected, "
                                   f"got {quote(data.get('format'))} version {quote(data.get('format_version'))}")
    try:
        run = RunFile.model_validate(data)
    except ValidationError as exc:
        msgs = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']} (received {quote(e.get('input'))})"
                         for e in exc.errors()[:10])
        raise RecordingFormatError(f"{path}: {msgs}") from None
    if run.transducer.sensitivity_V_per_N == 0:
        raise RecordingFormatError(f"{path}: transducer.sensitivity_V_per_N must not be 0")
    if run.format_version == 1:
        extra = ([f"steps.{i}.crank_radius_m" for i, st in enumerate(run.steps) if st.crank_radius_m is not None]
                 + (["rig"] if run.rig is not None else []))
        if extra:
            raise RecordingFormatError(f"{path}: {', '.join(extra)}: not part of version 1 (one crank radius per "
                                       "run); write format_version: 2")
        if run.crank_radius_m is None:
            raise RecordingFormatError(f"{path}: crank_radius_m: Field required (version 1: one radius per run)")
    missing = [i for i, st in enumerate(run.steps) if st.crank_radius_m is None and run.crank_radius_m is None]
    if missing:
        raise RecordingFormatError(f"{path}: steps.{missing[0]}.crank_radius_m: no crank radius for this step "
                                   "(give it, or crank_radius_m for the whole run)")
    return run, text


def step_radius(run: RunFile, step: CsvStep) -> float:
    """The crank radius of a step (m): its own (v2), else the run's."""
    r = step.crank_radius_m if step.crank_radius_m is not None else run.crank_radius_m
    assert r is not None  # checked when the file was read
    return r


def _nonblank(text: str) -> Iterator[tuple[int, str]]:
    """(1-based line number in the file, text) of the non-blank lines, lazily (a large file is never
    held twice as a list of lines)."""
    for i, ln in enumerate(io.StringIO(text), start=1):
        if ln.strip():
            yield i, ln.rstrip("\r\n")


_PLAIN_ROWS = re.compile(r"[0-9eE+\-.,\n]*")  # digits, signs, points, exponents, commas, newlines only


def _plain_body(text: str) -> str | None:
    """The data lines of a step file as one text when nothing in them needs ``_nonblank``: the header
    is the first line and the rest holds no blank line, no carriage return and no other characters
    than numbers, commas and newlines (the parser then reads it as it reads the lines one by one);
    else None."""
    end = text.find("\n")
    if end < 0:
        return None
    body = text[end + 1 :]
    if body.startswith("\n") or "\n\n" in body or _PLAIN_ROWS.fullmatch(body) is None:
        return None
    return body


def _first_bad_line(path: Path, lines: Iterator[tuple[int, str]]) -> str:
    """Locate the first malformed data line among ``lines`` (the data lines, ``_nonblank``)."""
    for i, line in lines:
        cells = line.split(",")
        if len(cells) != 3:
            return f"{path}, line {i}: 3 cells expected, got {len(cells)} ({quote(line)})"
        for name, cell in zip(HEADER.split(","), cells, strict=True):
            try:
                v = float(cell)
            except ValueError:
                return f"{path}, line {i}: column {name}: a number expected, got {quote(cell.strip())}"
            if not np.isfinite(v):
                return f"{path}, line {i}: column {name}: a finite number expected, got {quote(cell.strip())}"
        try:  # what float() takes but the CSV parser does not (e.g. '1_0')
            np.loadtxt([line], delimiter=",", dtype=np.float64, comments=None)
        except ValueError:
            return f"{path}, line {i}: three plain numbers expected, got {quote(line)}"
    return f"{path}: malformed CSV"


def read_step_csv(path: Path, sample_rate_hz: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Parse and check one step file (at most ``MAX_STEP_FILE_BYTES``); returns (displacement_m,
    force_V, t0_s).  Blank lines are skipped; error messages give line numbers in the file as it is."""
    text = read_text_limited(path, MAX_STEP_FILE_BYTES, "step file", RecordingFormatError)
    header = next(_nonblank(text), None)
    if header is None or header[1].strip().replace(" ", "") != HEADER:
        got = header[1].strip() if header else "an empty file"
        raise RecordingFormatError(f"{path}, line {header[0] if header else 1}: header {HEADER!r} "
                                   f"expected, got {quote(got)}")

    def data_lines() -> Iterator[tuple[int, str]]:
        lines = _nonblank(text)
        next(lines)  # the header
        return lines

    plain = _plain_body(text) if header[0] == 1 else None
    try:
        data = np.loadtxt(io.StringIO(plain) if plain is not None else (ln for _, ln in data_lines()),
                          delimiter=",", dtype=np.float64, ndmin=2, comments=None)
    except ValueError:
        raise RecordingFormatError(_first_bad_line(path, data_lines())) from None
    if data.shape[0] < 2:
        raise RecordingFormatError(f"{path}: at least 2 samples expected, got {data.shape[0]}")
    if data.shape[1] != 3 or not np.all(np.isfinite(data)):
        raise RecordingFormatError(_first_bad_line(path, data_lines()))
    t = data[:, 0]
    dt = np.diff(t)
    T = 1.0 / sample_rate_hz
    med = float(np.median(dt))
    if abs(med - T) > RATE_TOLERANCE * T:
        raise RecordingFormatError(
            f"{path}: sample interval {med:.9g} s ({1 / med if med > 0 else float('inf'):.6g} Hz) found, "
            f"RUN.yaml says sample_rate_hz {sample_rate_hz:g} (interval {T:.9g} s)")
    bad = np.nonzero(np.abs(dt - T) > RATE_TOLERANCE * T)[0]
    if bad.size:
        i = int(bad[0])
        line_no = next(n for k, (n, _) in enumerate(data_lines()) if k == i + 1)
        raise RecordingFormatError(
            f"{path}, line {line_no}: non-uniform time: t_s steps by {dt[i]:.9g} s from the line "
            f"before, {T:.9g} s expected")
    return data[:, 1].copy(), data[:, 2].copy(), float(t[0])


def step_file(src: Path, name: str) -> Path:
    """A step file RUN.yaml names: beside it, a regular file (never a FIFO, a device or a symlink
    loop, which would hang or fail the import)."""
    try:
        f = (src.parent / name).resolve()
        if src.parent.resolve() not in f.parents:
            raise RecordingFormatError(f"{src}: step file {name!r} must lie beside RUN.yaml")
        mode = f.stat().st_mode
    except FileNotFoundError as exc:
        raise RecordingFormatError(f"{f}: cannot read: {exc.strerror}") from None
    except (OSError, RuntimeError) as exc:  # RuntimeError: a symlink loop (Python < 3.13)
        raise RecordingFormatError(f"{src}: step file {name!r} cannot be opened ({exc})") from None
    if not stat.S_ISREG(mode):
        raise RecordingFormatError(f"{src}: step file {name!r} is not a regular file (a FIFO, a device or a "
                                   "folder); refused")
    return f


def import_run(run_yaml: str | Path, out_dir: str | Path) -> Path:
    """Convert a sinecal-csv run into a recording in ``out_dir``; returns its path."""
    src = Path(run_yaml)
    run, run_text = _load_run_file(src)
    files = [step_file(src, st.file) for st in run.steps]  # every file checked before any is read
    total = sum(f.stat().st_size for f in files)
    if total > MAX_RUN_BYTES:
        raise RecordingFormatError(f"{src}: its {len(files)} step files add up to {total} bytes (a file named n "
                                   f"times counts n times); the limit is {MAX_RUN_BYTES} bytes per run")
    steps = [(st, *read_step_csv(f, run.sample_rate_hz)) for st, f in zip(run.steps, files, strict=True)]
    meta = RunMetadata(
        run_id=new_run_id(run.transducer.id), transducer_id=run.transducer.id, source="import",
        sample_rate_hz=run.sample_rate_hz, load_mass_kg=run.top_mass_kg, end_mass_kg=run.end_mass_kg,
        sensitivity_V_per_N=run.transducer.sensitivity_V_per_N, capacity_N=run.transducer.capacity_N,
        config_yaml=run_text)
    channels = (ChannelSpec("displacement", "f8", "m", "m", scale=1.0),
                ChannelSpec("force", "f8", "V", "V", scale=1.0))
    writer = RecordingWriter(out_dir, meta, channels,
                             plan={"kind": "import", "source": str(src), "format": FORMAT})
    try:
        for st, disp, force, t0 in steps:
            start = writer.samples_written
            writer.append(disp, force)
            writer.add_step(crank_frequency_hz=st.crank_frequency_hz, crank_radius_m=step_radius(run, st),
                            start_sample=start, end_sample=start + disp.size,
                            extra={"file": st.file, "t0_s": t0})
        return writer.finish("completed")
    except BaseException:
        writer.abandon()
        writer.partial_path.unlink(missing_ok=True)
        raise


def _stated_uncertainties(cfg: dict) -> dict:
    """The mass uncertainties and measurement chain a recording's configuration states explicitly,
    as RUN.yaml keys (defaults are not written)."""
    if cfg.get("format") == FORMAT:
        return {k: cfg[k] for k in ("end_mass_std_kg", "top_mass_std_kg", "measurement_chain") if k in cfg}
    out = {"end_mass_std_kg": (cfg.get("transducer") or {}).get("end_mass_std_kg"),
           "top_mass_std_kg": (cfg.get("rig") or {}).get("load_mass_std_kg"),
           "measurement_chain": (cfg.get("identification") or {}).get("chain")}
    chain = out["measurement_chain"]
    if isinstance(chain, dict) and MeasurementChain.model_validate(chain) == MeasurementChain():  # the defaults
        out["measurement_chain"] = None
    return {k: v for k, v in out.items() if v is not None}


def _rig_limits(cfg: dict) -> dict | None:
    """The rig limits a recording's configuration states (a station configuration's ``rig`` ranges,
    or an imported v2 RUN.yaml's ``rig``), as the RUN.yaml v2 ``rig`` mapping; None if it has none."""
    if cfg.get("format") == FORMAT:
        return cfg.get("rig")
    rig = cfg.get("rig") or {}
    from station.config import RigConfig

    try:
        limits = RigConfig.model_validate(rig)
    except ValidationError:
        return None
    return {"crank_frequency_hz": limits.crank_frequency_hz.model_dump(),
            "crank_radius_m": limits.crank_radius_m.model_dump(),
            "peak_force_fraction": limits.peak_force_fraction}


def write_step_csv(path: Path, columns: np.ndarray, rows_per_write: int = 20_000) -> None:
    """A step file: the header line, then one line per row of ``columns`` (shape (n, 3): t_s,
    displacement_m, force_V), each value as ``%.17g`` (exact round trip), comma-separated: the bytes
    ``np.savetxt(path, columns, delimiter=",", fmt="%.17g", header=HEADER, comments="")`` writes,
    formatted a block of rows at a time instead of row by row."""
    n_rows, n_cols = columns.shape
    line = ",".join(["%.17g"] * n_cols) + "\n"
    with open(path, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(HEADER + "\n")
        for start in range(0, n_rows, rows_per_write):
            block = columns[start:start + rows_per_write]
            fh.write((line * block.shape[0]) % tuple(block.ravel().tolist()))


def export_run(recording: str | Path, out_dir: str | Path) -> Path:
    """Write a recording's steps in the interchange format (version 2: a crank radius per step, the
    rig's limits when the recording states them) into a new folder ``<out_dir>/<run_id>/``; returns
    the path of its RUN.yaml.  Existing folders are refused."""
    rec = read_recording(recording)
    if not rec.steps:
        raise StationError(f"{rec.path}: the recording has no steps to export")
    target = Path(out_dir) / rec.run_id
    if target.exists():
        raise StationError(f"{target} exists already; not overwriting it")
    tmp = target.with_name(target.name + ".exporting")
    if tmp.exists():
        raise StationError(f"{tmp} exists: an earlier export of this run was cut off; "
                           f"remove that folder and export again")
    tmp.mkdir(parents=True)
    try:
        fs = rec.sample_rate_hz
        entries = []
        for s in rec.steps:
            name = f"step{s.index:02d}.csv"
            n = np.arange(s.start_sample, s.end_sample)
            d, fv = rec.step_signals(s)
            write_step_csv(tmp / name, np.column_stack([n / fs, d, fv]))
            entries.append({"file": name, "crank_frequency_hz": s.crank_frequency_hz,
                            "crank_radius_m": s.crank_radius_m})
        rig = _rig_limits(rec.config)
        doc = {"format": FORMAT, "format_version": VERSION, "sample_rate_hz": fs,
               "top_mass_kg": rec.load_mass_kg,
               **({"end_mass_kg": rec.end_mass_kg} if rec.end_mass_kg is not None else {}),
               **_stated_uncertainties(rec.config),
               **({"rig": rig} if rig is not None else {}),
               "transducer": {"id": rec.transducer_id, "capacity_N": rec.capacity_N,
                              "sensitivity_V_per_N": rec.sensitivity_V_per_N},
               "steps": entries}
        (tmp / "RUN.yaml").write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
        os.replace(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target / "RUN.yaml"
