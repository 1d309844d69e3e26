"""The calibration report as a figure-based PDF (matplotlib's PdfPages, no further dependency).

Page 1 is a text summary (conditions, parameters with u and U, dynamic sensitivity per step), then
one page per plot of PLOT_NAMES.  The HTML page is the complete report; the PDF is for filing and
printing.  It carries no creation date, so the same recording gives the same bytes.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure

from station import __version__
from station.report.data import RunData, load_run
from station.report.plots import PLOT_NAMES, make_figure
from station.report.quantities import COVERAGE_K, fmt_unc, fmt_value, measured_sensitivity

A4_IN = (8.27, 11.69)


def summary_lines(d: RunData) -> list[str]:
    """The text of the summary page."""
    rec, ident = d.rec, d.ident
    lost = int(rec.lost_samples[:, 1].sum()) if rec.lost_samples.size else 0
    lines = [f"transducer {rec.transducer_id}   run {rec.run_id}",
             f"start {rec.start_time}   end {rec.end_time or '-'}",
             f"exit status {rec.exit_status}{f' ({rec.reason})' if rec.reason else ''}   lost samples {lost}",
             f"load mass m_l {rec.load_mass_kg:g} kg   end mass m_e "
             f"{'unknown' if rec.end_mass_kg is None else f'{rec.end_mass_kg:g} kg'}   M {d.mass_kg:g} kg",
             f"software {rec.software_version or '?'} (report {__version__})",
             f"method {ident.method}   model {ident.model}",
             f"result: {d.ident_source}", "",
             "steps:  f (Hz)   radius (mm)   lost in window"]
    lines += [f"  {s.index:3d}  {s.crank_frequency_hz:8.4g}   {1e3 * s.crank_radius_m:8.4g}   {s.lost_in_window}"
              for s in rec.steps]
    lines += ["", "parameter   value            u (k = 1)   U (k = 2)   unit"]
    for name, p in ident.parameters.items():
        if not p.identifiable or p.value is None:
            lines.append(f"  {name:6s}    not identifiable: {p.reason}")
            continue
        u = p.std
        lines.append(f"  {name:6s}    {fmt_value(p.value, u):15s}  {fmt_unc(u):10s}  "
                     f"{fmt_unc(None if u is None else COVERAGE_K * u):10s}  {p.unit}")
    r = d.response
    mag, u_mag, ph, u_ph = measured_sensitivity(r.H, r.cov, d.mass_kg)
    lines += ["", "dynamic sensitivity S_dyn = -H/M (measured):", "  f (Hz)     |S_dyn| (V/N)   U (k = 2)"
              "    phase (deg)   U (k = 2)"]
    lines += [f"  {f:8.4g}   {fmt_value(mag[i], u_mag[i]):14s}  {fmt_unc(COVERAGE_K * u_mag[i]):10s}   "
              f"{np.degrees(ph[i]):10.4f}    {fmt_unc(COVERAGE_K * np.degrees(u_ph[i]))}"
              for i, f in enumerate(r.f_hz)]
    if d.discrepancy:
        lines += ["", f"discrepancy: gap {fmt_unc(d.discrepancy.get('base_gap'))} V -> "
                      f"{fmt_unc(d.discrepancy.get('final_gap'))} V; effects: "
                      + (", ".join(str(e.get("name")) for e in d.discrepancy.get("effects") or []) or "none")]
        lines += [f"  unexplained: {u}" for u in d.discrepancy.get("unexplained") or []]
        lines += [f"  {t.get('kind', 'tie')}: {t.get('message', '')}" for t in d.discrepancy.get("ties") or []]
    lines += [f"note: {n}" for n in ident.notes]
    lines += [f"check {c.severity}: {c.name}: {c.message}" for c in ident.checks]
    em = ident.assumptions.get("end_mass_kg")
    if em:
        lines.append(f"end mass {em.get('value')} kg ({em.get('source')}"
                     + (f", u = {fmt_unc(em['std'])} kg)" if em.get("std") is not None
                        else "; results conditional on it)"))
    for n, b in ident.budget.items():
        lines.append(f"budget {n}: " + ", ".join(f"{k} {fmt_unc(v) if v is not None else 'conditional'}"
                                                 for k, v in b["contributions"].items())
                     + f"; combined {fmt_unc(b['combined'])} {b.get('unit', '')}")
    return lines


def render_report_pdf(recording_path: Path) -> bytes:
    """The report as PDF bytes: a summary page, then the plots."""
    d = load_run(recording_path)
    buf = io.BytesIO()
    with PdfPages(buf, metadata={"Creator": f"sinecal {__version__}", "CreationDate": None}) as pdf:
        fig = Figure(figsize=A4_IN)
        FigureCanvasAgg(fig)
        fig.text(0.06, 0.96, "Calibration report", fontsize=16, va="top")
        fig.text(0.06, 0.92, "\n".join(summary_lines(d)), family="monospace", fontsize=7, va="top")
        pdf.savefig(fig)
        for name in PLOT_NAMES:
            pdf.savefig(make_figure(d, name))
    return buf.getvalue()
