"""A recording's results as tables for a spreadsheet: the identified parameters with their standard
uncertainties, and the dynamic sensitivity S_dyn(f) = -H(f)/M of the measured steps with its
uncertainties; as CSV (one file per table) and as an Excel workbook (openpyxl: a sheet per table and
one saying where they come from).

Every column that holds a quantity names its unit in its header (``f (Hz)``, ``|S_dyn| (V/N)``);
a parameter's unit, which differs from row to row, is in its own ``unit`` column beside value and
uncertainty.  u is the standard uncertainty (k = 1), U the expanded one (k = 2), as in the report.
The tables are read from the stored identification (``station.report.data.load_run``), never a new fit.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from station.report.data import RunData, load_run
from station.report.quantities import COVERAGE_K, measured_sensitivity
from station.report.tables import MEANING

PARAMETER_HEADER = ("parameter", "quantity", "value", "standard uncertainty u (k = 1)", "unit", "identified",
                    "flag", "note")
SDYN_HEADER = ("step", "f (Hz)", "|S_dyn| (V/N)", "u(|S_dyn|) (V/N)", "U(|S_dyn|), k = 2 (V/N)",
               "phase of S_dyn (°)", "u(phase) (°)", "U(phase), k = 2 (°)")
Row = tuple[Any, ...]


@dataclass(frozen=True)
class ResultTables:
    """The tables of one recording: header and rows each, and what they come from (``about``: label, text)."""

    parameters: tuple[Row, ...]
    sdyn: tuple[Row, ...]
    about: tuple[tuple[str, str], ...]


def _num(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(float(x)) else float(x)


def result_tables(path: str | Path) -> ResultTables:
    """The tables of the recording at ``path`` (RecordingFormatError when it has no results)."""

    d: RunData = load_run(path)
    ident = d.ident
    params = tuple((name, MEANING.get(name, name), _num(p.value), _num(p.std), p.unit, "yes" if p.identifiable
                    else "no", p.flag, p.reason) for name, p in ident.parameters.items())
    r = d.response
    mag, u_mag, ph, u_ph = measured_sensitivity(r.H, r.cov, d.mass_kg, ident.assumptions.mass_std_kg)
    sdyn = tuple((r.step_index[i] + 1, float(f), _num(float(mag[i])), _num(float(u_mag[i])),
                  _num(COVERAGE_K * float(u_mag[i])), _num(math.degrees(float(ph[i]))),
                  _num(math.degrees(float(u_ph[i]))), _num(math.degrees(COVERAGE_K * float(u_ph[i]))))
                 for i, f in enumerate(r.f_hz))
    about = (("recording", Path(path).name), ("transducer", str(d.rec.transducer_id)),
             ("method", f"{ident.method}, model {ident.model}"), ("identification stored as", d.ident_source),
             ("moving mass M = m_e + m_l (kg)", f"{d.mass_kg:.6g}"),
             ("S_dyn", "S_dyn(f) = -H(f)/M, the force signal per inertial force of the moving masses; steps "
                       "counted from 1"),
             ("uncertainties", "u: standard uncertainty (k = 1); U: expanded uncertainty (k = 2)"))
    return ResultTables(params, sdyn, about)


def _csv(header: Row, rows: tuple[Row, ...]) -> bytes:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\r\n")
    w.writerow(header)
    w.writerows(["" if v is None else v for v in row] for row in rows)
    return buf.getvalue().encode("utf-8-sig")  # the BOM: spreadsheets read '°' and '±' right


def parameters_csv(t: ResultTables) -> bytes:
    return _csv(PARAMETER_HEADER, t.parameters)


def sdyn_csv(t: ResultTables) -> bytes:
    return _csv(SDYN_HEADER, t.sdyn)


def workbook(t: ResultTables) -> bytes:
    """The tables as an Excel workbook (.xlsx): sheets ``parameters``, ``S_dyn``, ``about``."""
    from openpyxl import Workbook
    from openpyxl.styles import Font

    wb = Workbook()
    sheets = (("parameters", PARAMETER_HEADER, t.parameters), ("S_dyn", SDYN_HEADER, t.sdyn),
              ("about", ("item", "value"), t.about))
    for i, (title, header, rows) in enumerate(sheets):
        ws = wb.active if i == 0 else wb.create_sheet()
        assert ws is not None
        ws.title = title
        ws.append(list(header))
        for cell in ws[1]:
            cell.font = Font(bold=True)
        for row in rows:
            ws.append(list(row))
        for col, name in zip(ws.columns, header, strict=False):
            width = max([len(str(name)), *(len(str(c.value)) for c in col if c.value is not None)])
            ws.column_dimensions[col[0].column_letter].width = min(60, width + 2)
        ws.freeze_panes = "A2"
    out = io.BytesIO()
    wb.save(out)
    return out.getvalue()


EXPORTS = {"parameters.csv": parameters_csv, "sdyn.csv": sdyn_csv, "results.xlsx": workbook}


def export_bytes(path: str | Path, name: str) -> bytes:
    """One export (a key of :data:`EXPORTS`) of the recording at ``path``."""
    return EXPORTS[name](result_tables(path))


def write_exports(path: str | Path, out_dir: str | Path) -> list[Path]:
    """Every export of the recording, written beside each other in ``out_dir`` as
    ``<recording stem>.<name>``; the paths written."""
    t = result_tables(path)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, fn in EXPORTS.items():
        target = out / f"{Path(path).stem}.{name}"
        target.write_bytes(fn(t))
        written.append(target)
    return written
