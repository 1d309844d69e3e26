"""The report's multi-mass campaign section: the joint identification stored as ``results/campaign``
by ``station identify REC1 REC2 ...`` or ``POST /campaigns`` with ``store``, shown in the report of
every recording that took part (docs/identification.md, "Multi-mass campaign")."""

from __future__ import annotations

from typing import Any

from station.ident.result import estimates_from_dict
from station.report.data import RunData
from station.report.quantities import fmt_unc, fmt_value, structure_sentence
from station.report.tables import PARAM_HEADERS, budget_table, esc, num, param_rows, table

STATUS = {"separated": "S and the end mass m_e separated by the top masses",
          "conditional": "the top masses are too alike to separate S from m_e: S, k_f, b_f are given on the "
                         "stated end mass (its uncertainty propagated), m_e is not given",
          "refused": "no S, m_e, k_f, b_f: see the checks and what the data determine"}


def campaign_section(d: RunData) -> str:
    """HTML of the stored campaign result, or '' when this recording took part in none."""
    stored = d.results.get("campaign")
    if stored is None:
        return ""
    c: dict[str, Any] = stored.payload
    this = d.rec.run_id
    rec_rows = [[esc(r.get("run_id", "")) + (" (this run)" if r.get("run_id") == this else ""),
                 num(fmt_value(r["load_mass_kg"]["value"], r["load_mass_kg"]["std"]), r["load_mass_kg"]["value"]),
                 num(fmt_unc(r["load_mass_kg"]["std"])),
                 num(f"{r['f_range_hz'][0]:.4g}–{r['f_range_hz'][1]:.4g}"), num(str(len(r["steps_used"]))),
                 num(f"{r['chi2']:.3g}" if r.get("chi2") is not None else "n/a")]
                for r in c.get("recordings") or []]
    checks = "".join(f"<li><b>{esc(k['severity'])}</b> {esc(k['name'])}: {esc(k['message'])}</li>"
                     for k in c.get("checks") or [])
    fit = c.get("fit") or {}
    chi = fit.get("chi2_per_dof")
    fit_note = "" if chi is None else (
        f'<p class="note">χ²/dof {chi:.3g} ({fit.get("chi2", 0):.4g} on {fit.get("dof")})'
        + (", uncertainties inflated by √(χ²/dof)" if fit.get("inflated") else "") + "</p>")
    notes = "".join(f"<li>{esc(n)}</li>" for n in c.get("notes") or [])
    st = (c.get("assumptions") or {}).get("structure")
    structure = (f'<p class="note" data-structure="campaign">Model structure: {esc(structure_sentence(st))}</p>'
                 if st else "")
    params = estimates_from_dict(c.get("parameters"))
    det = c.get("determined") or {}
    det_rows = [[esc(r.get("run_id", "")), esc(name), num(fmt_value(r.get("value"), r.get("combined")), r.get("value")),
                 num(fmt_unc(r.get("combined"))), esc(r.get("unit", ""))]
                for name, rows in det.items() for r in rows]
    det_html = ("<h3>What each recording determines whatever the end mass</h3>"
                + table(["run", "quantity", "value", "u (k = 1)", "unit"], det_rows)) if det_rows else ""
    return (f"<h2>Multi-mass campaign</h2><p>Joint identification (Eq. 9, one S, m_e, k_f, b_f) of "
            f"{len(rec_rows)} recording(s) of {esc(c.get('transducer_id', ''))}, written {esc(stored.written)}: "
            f"<b>{esc(c.get('status', ''))}</b> — {esc(STATUS.get(str(c.get('status')), ''))}.</p>"
            + table(PARAM_HEADERS, param_rows(params, "campaign."), "campaign")
            + budget_table(c.get("budget") or {}, "campaign.budget.")
            + "<h3>Recordings</h3>"
            + table(["run", "load mass m_l (kg)", "u (kg)", "frequencies (Hz)", "steps", "χ² share"], rec_rows)
            + fit_note + structure + det_html
            + (f'<h3>Campaign checks</h3><ul class="note">{checks}</ul>' if checks else "")
            + (f'<ul class="note">{notes}</ul>' if notes else ""))
