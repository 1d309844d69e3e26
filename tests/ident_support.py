"""Runs for the identification tests, made by the project's simulator (station.simulate: Eq. 3
integrated with whatever effects the case switches on) and, where a case is about runs recorded
elsewhere, written out and read back through the sinecal-csv import path (export -> edit -> import).
Truth: the simulator's configuration (k_f 2.91e7 N/m, b_f 17136 N*s/m, S 2e-3 V/N, m_e 0.12 kg,
m_l 26.167 kg)."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from station.config import parse_config
from station.interchange import export_run, import_run
from station.simulate import simulate_run
from tests.conftest import station_dict

K, B, S, ME, ML = 2.91e7, 17136.0, 2e-3, 0.12, 26.167
R = 2.5e-4  # sinecal-csv has one crank radius per run: the largest the 100 Hz step allows
PLAN = tuple((f, R) for f in (4.0, 12.0, 30.0, 60.0, 100.0))


def sim(folder: Path, steps: tuple[tuple[float, float], ...] = PLAN, *, seed: int = 3, record_s: float = 1.0,
        edit: Callable[[dict[str, Any]], None] | None = None) -> Path:
    data = station_dict(settle_s=0.3, record_s=record_s, steps=steps, acceleration_hz_per_s=200.0, pre_roll_s=0.1)
    if edit:
        edit(data)
    return simulate_run(parse_config(data), folder, seed=seed)


_EXPORTS: dict[tuple[str, int, int], Path] = {}  # recording -> the folder of its untouched export


def _exported(rec: Path, out_dir: Path) -> Path:
    """``export_run(rec, out_dir)``, the folder copied from an earlier export of the same recording."""
    st = rec.stat()
    key = (str(rec.resolve()), st.st_mtime_ns, st.st_size)
    src = _EXPORTS.get(key)
    if src is None or not src.is_dir():
        src = export_run(rec, out_dir.with_name(out_dir.name + "-untouched")).parent
        _EXPORTS[key] = src
    dst = out_dir / src.name
    shutil.copytree(src, dst)
    return dst / "RUN.yaml"


def via_csv(rec: Path, folder: Path, *, doc: Callable[[dict[str, Any]], None] | None = None,
            step: dict[int, Callable[[np.ndarray], np.ndarray]] | None = None) -> Path:
    """Export a simulated recording as sinecal-csv, edit RUN.yaml and step files, import it back.  A
    recording exported before (same path, modification time and size) is copied from that export's
    untouched folder instead of being written again (the same bytes)."""
    run = _exported(rec, folder / "csv")
    d = yaml.safe_load(run.read_text(encoding="utf-8"))
    if doc:
        doc(d)
    run.write_text(yaml.safe_dump(d, sort_keys=False), encoding="utf-8")
    for i, fn in (step or {}).items():
        f = run.parent / d["steps"][i]["file"]
        a = np.loadtxt(f, delimiter=",", skiprows=1)
        np.savetxt(f, fn(a), delimiter=",", fmt="%.17g", header="t_s,displacement_m,force_V", comments="")
    return import_run(run, folder / "imported")
