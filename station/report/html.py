"""The calibration report of a run as one self-contained HTML page (plots embedded as base64 PNG,
styles inline, no external assets).  Layout and definitions: docs/report.md."""

from __future__ import annotations

import base64
import html
import logging
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from station import __version__
from station.ident.result import Estimate, estimates_from_dict
from station.report.data import RunData, load_run
from station.report.plots import PLOT_NAMES, render_plot
from station.report.quantities import (
    COVERAGE_K,
    fmt_rel,
    fmt_unc,
    fmt_value,
    measured_sensitivity,
    model_sensitivity,
    range_text,
    structure_sentence,
)

log = logging.getLogger(__name__)
MODELS = {
    "sdof": "stiff coupling, paper Eq. 9: H(s) = −S·M·k_f / (M s² + b_f s + k_f), M = m_e + m_l",
    "coupled": "finite coupling stiffness k_c and damping b_c, paper Eq. 8 (fourth order)",
    "h2": "the paper's digital Eq. 11 (bilinear transform of Eq. 9), mapped to S, k_f, b_f with the known masses",
    "h1": "the paper's digital Eq. 10 (bilinear transform of Eq. 8), mapped with the known masses",
}
METHODS = {
    "fd": "sine fits per step → H(f) → linear start on 1/H → weighted Levenberg–Marquardt (frequency domain)",
    "oe": "output error: Levenberg–Marquardt on the raw force samples of every step (time domain)",
    "pso": "the paper's particle swarm, PSO (Eq. 12–15), on one step cut as in Section 5.1",
    "pso+": "the paper's particle swarm, PSO+ (Eq. 12–16), on one step cut as in Section 5.1",
    "rls": "the paper's recursive least squares (Eq. 17) on one step cut as in Section 5.1",
}
MEANING = {"S": "sensitivity of the force signal (static limit of S_dyn)", "m_e": "end mass of the transducer",
           "k_f": "transducer stiffness",
           "b_f": "transducer damping", "k_c": "coupling stiffness", "b_c": "coupling damping"}
CSS = """body{font-family:sans-serif;max-width:1000px;margin:2em auto;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.2em}td,th{border:1px solid #bbb;padding:3px 8px;text-align:left}
th{background:#eee}td.num{text-align:right;font-family:monospace}.na{color:#a33}.note{color:#555;font-size:90%}
img{max-width:100%;border:1px solid #ddd;margin:.5em 0}h2{border-bottom:2px solid #ccc;padding-bottom:2px}"""


def _e(x: Any) -> str:
    return html.escape(str(x))


def _num(text: str, value: float | None = None, key: str = "") -> str:
    attrs = f' data-value="{float(value)!r}"' if value is not None and np.isfinite(value) else ""
    attrs += f' data-key="{_e(key)}"' if key else ""
    return f'<td class="num"{attrs}>{_e(text)}</td>'


def _table(headers: list[str], rows: list[list[str]], cls: str = "") -> str:
    head = "".join(f"<th>{h}</th>" for h in headers)
    body = "".join("<tr>" + "".join(c if c.startswith("<td") else f"<td>{c}</td>" for c in r) + "</tr>"
                   for r in rows)
    return f'<table class="{cls}"><tr>{head}</tr>{body}</table>'


def _conditions(d: RunData) -> str:
    rec = d.rec
    cfg = rec.config if isinstance(rec.config, dict) else {}
    rig, tr, cond = ((v if isinstance(v, dict) else {}) for v in (cfg.get(k) for k in ("rig", "transducer",
                                                                                       "conditioner")))
    top = rig.get("top_mass_kg")  # an imported run's RUN.yaml has only top_mass_kg = the load mass
    lost = rec.lost_samples
    rows = [["transducer id", _e(rec.transducer_id)],
            ["capacity", f"{rec.capacity_N:g} N"],
            ["nominal sensitivity of the force signal", f"{rec.sensitivity_V_per_N:.6g} V/N"
             + (f" (bridge {tr['sensitivity_V_per_N']:g} V/N × conditioner gain {cond['gain']:g})"
                if isinstance(tr.get("sensitivity_V_per_N"), int | float) and isinstance(cond.get("gain"), int | float)
                else "")],
            ["top mass", f"{top:g} kg" if isinstance(top, int | float) else "not recorded separately"],
            ["load mass m_l (top mass + adaption)", f"{rec.load_mass_kg:g} kg"],
            ["end mass m_e", f"{rec.end_mass_kg:g} kg" if rec.end_mass_kg is not None else
             "not given: S, k_f, b_f are conditional on the assumed value (see the identification)"],
            ["sample rate", f"{rec.sample_rate_hz:g} Hz"],
            ["source", _e(rec.source)],
            ["run id", _e(rec.run_id)],
            ["start / end (UTC)", f"{_e(rec.start_time)} / {_e(rec.end_time or '-')}"],
            ["exit status", _e(rec.exit_status + (f" ({rec.reason})" if rec.reason else ""))],
            ["lost samples", f"{int(lost[:, 1].sum()) if lost.size else 0} in {len(lost)} gap(s)"],
            ["software version (recording / report)", f"{_e(rec.software_version or '?')} / {_e(__version__)}"]]
    steps = [[str(s.index), _num(f"{s.crank_frequency_hz:g}", s.crank_frequency_hz),
              _num(f"{1e3 * s.crank_radius_m:g}", s.crank_radius_m),
              _num(f"{(s.end_sample - s.start_sample) / rec.sample_rate_hz:g}"), _num(str(s.lost_in_window)),
              "yes" if s.usable else '<span class="na">no: samples lost in the window</span>']
             for s in rec.steps]
    return ("<h2>Transducer and run conditions</h2>" + _table(["", ""], rows)
            + "<h3>Steps</h3>" + _table(["step", "crank frequency (Hz)", "crank radius (mm)", "record window (s)",
                                         "lost samples in window", "used"], steps))


def _model(d: RunData) -> str:
    ident = d.ident
    fit = ident.fit
    rms = ", ".join(fmt_unc(v) for v in fit.residual_rms_V)
    rows = [["method", f"{_e(ident.method)}: {_e(METHODS.get(ident.method, ''))}"],
            ["model", f"{_e(ident.model)}: {_e(MODELS.get(ident.model, ''))}"],
            ["result", _e(d.ident_source)],
            ["masses used", f"M = m_e + m_l = {d.mass_kg:g} kg"],
            ["fit", f"MSE {fmt_unc(fit.mse)} V², residual RMS per step [{rms}] V, "
                    f"χ²/dof {fmt_unc(fit.chi2_per_dof)}, {fit.n_points or '?'} points"],
            ["condition number", fmt_unc(None if ident.identifiability is None
                                         else ident.identifiability.condition_number)]]
    for name, a in ident.assumptions.items():
        if isinstance(a, dict) and "source" in a:
            rows.append([_e(name), f"{a.get('value')} ({_e(a['source'])}"
                         + (f", u = {fmt_unc(a['std'])})" if a.get("std") is not None
                            else "; no uncertainty: the results are conditional on it)")])
    st = ident.assumptions.get("structure")
    if st:
        rows.append(["model structure", _e(structure_sentence(st))])
    notes = "".join(f"<li>{_e(n)}</li>" for n in ident.notes)
    checks = "".join(f'<li data-check="{_e(c.name)}">{_e(c.severity)}: {_e(c.name)}'
                     f'{"" if c.step is None else " (step " + str(c.step) + ")"}: {_e(c.message)}</li>'
                     for c in ident.checks)
    det = [[_e(k), _num(fmt_value(v.get("value"), v.get("combined")), v.get("value")), _num(fmt_unc(v.get("combined"))),
            _e(v.get("unit", ""))] if "range" not in v else
           [_e(k), _e(range_text(v["range"])), _e(v.get("conditional_on", "")), _e(v.get("unit", ""))]
           for k, v in ident.determined.items()]
    return ("<h2>Model and identification</h2>" + _table(["", ""], rows)
            + (f'<h3>Input checks</h3><ul class="note">{checks}</ul>' if checks else "")
            + (("<h3>What the data determine whatever the end mass and the coupling</h3>"
                + _table(["quantity", "value", "u (k = 1)", "unit"], det)) if det else "")
            + (f'<ul class="note">{notes}</ul>' if notes else ""))


def _param_rows(params: Mapping[str, Estimate], prefix: str) -> list[list[str]]:
    rows = []
    for name, p in params.items():
        unit = _e(p.unit)
        if not p.identifiable or p.value is None:
            why = p.reason or "no value"
            rows.append([_e(name), _e(MEANING.get(name, "")),
                         f'<td colspan="5" class="na" data-key="{prefix}{_e(name)}">not identifiable: {_e(why)}</td>',
                         unit])
            continue
        v, u = float(p.value), p.std
        meaning = _e(MEANING.get(name, "")) + (f' <span class="na">({_e(p.flag)}: {_e(p.reason)})</span>'
                                               if p.flag else "")
        rows.append([_e(name), meaning, _num(fmt_value(v, u), v, f"{prefix}{name}"),
                     _num(fmt_unc(u), u, f"{prefix}{name}.u"),
                     _num(fmt_unc(COVERAGE_K * u) if u is not None else "n/a",
                          COVERAGE_K * u if u is not None else None, f"{prefix}{name}.U"),
                     _num(fmt_rel(v, COVERAGE_K * u if u is not None else None)),
                     _num("" if u is None else f"{fmt_value(v, u)} ± {fmt_unc(COVERAGE_K * u)}"), unit])
    return rows


PARAM_HEADERS = ["parameter", "meaning", "value", "u (k = 1)", "U (k = 2)", "U rel. (%)", "value ± U (k = 2)",
                 "unit"]


def _budget(d: RunData) -> str:
    """GUM budget: standard uncertainty of each parameter per source (k = 1), and combined."""
    return _budget_table(d.ident.budget, "budget.")


def _budget_table(budget: dict[str, Any], prefix: str) -> str:
    if not budget:
        return ""
    sources = list(next(iter(budget.values()))["contributions"])
    rows = [[_e(n)] + [_num(fmt_unc(b["contributions"].get(s)) if b["contributions"].get(s) is not None
                            else "conditional") for s in sources]
            + [_num(fmt_unc(b["combined"]), b["combined"], f"{prefix}{n}"), _e(b.get("unit", ""))]
            for n, b in budget.items()]
    return ("<h3>Uncertainty budget (standard uncertainties, k = 1)</h3>"
            + _table(["parameter", *[_e(s) for s in sources], "combined", "unit"], rows))


def _parameters(d: RunData) -> str:
    return ("<h2>Identified parameters</h2>" + _table(PARAM_HEADERS, _param_rows(d.ident.parameters,
                                                                                 "param."), "params")
            + _budget(d))


def _sensitivity(d: RunData) -> str:
    r = d.response
    mag, u_mag, ph, u_ph = measured_sensitivity(r.H, r.cov, d.mass_kg)
    model = model_sensitivity(d.curve, r.f_hz) if d.curve is not None else None
    if model is not None:
        ph = model[2] + np.angle(np.exp(1j * (ph - model[2])))
    rows = []
    for i, f in enumerate(r.f_hz):
        row = [str(r.step_index[i]), _num(f"{f:.6g}", f),
               _num(fmt_value(mag[i], u_mag[i]), mag[i], f"sdyn.{i}"), _num(fmt_unc(u_mag[i])),
               _num(fmt_unc(COVERAGE_K * u_mag[i])),
               _num(fmt_value(np.degrees(ph[i]), np.degrees(u_ph[i])), np.degrees(ph[i]), f"phase.{i}"),
               _num(fmt_unc(np.degrees(u_ph[i]))), _num(fmt_unc(COVERAGE_K * np.degrees(u_ph[i])))]
        if model is not None:
            m_mag, m_umag, m_ph, m_uph = model
            row += [_num(fmt_value(m_mag[i], None if m_umag is None else m_umag[i]), m_mag[i]),
                    _num("n/a" if m_umag is None else fmt_unc(COVERAGE_K * m_umag[i])),
                    _num(fmt_value(np.degrees(m_ph[i]), None if m_uph is None else np.degrees(m_uph[i]))),
                    _num("n/a" if m_uph is None else fmt_unc(COVERAGE_K * np.degrees(m_uph[i])))]
        rows.append(row)
    head = ["step", "f (Hz)", "|S_dyn| (V/N)", "u (V/N)", "U, k = 2 (V/N)", "phase (°)", "u (°)", "U, k = 2 (°)"]
    if model is not None:
        head += ["model |S_dyn| (V/N)", "model U, k = 2 (V/N)", "model phase (°)", "model U, k = 2 (°)"]
    note = (f"S_dyn(f) = −H(f)/M with M = {d.mass_kg:g} kg: force signal per inertial force of the moving "
            f"masses. Measured points from {r.source}.")
    extra = d.curve.note if d.curve is not None else d.curve_note
    if extra:
        note += f" {extra[0].upper()}{extra[1:]}."
    return ("<h2>Dynamic sensitivity and phase versus frequency</h2>" + _table(head, rows, "sdyn")
            + f'<p class="note">{_e(note)}</p>')


def _plots(path: Path) -> str:
    out = ["<h2>Plots</h2>"]
    for name in PLOT_NAMES:
        png = base64.b64encode(render_plot(path, name)).decode("ascii")
        out.append(f'<h3>{_e(name)}</h3><img alt="{_e(name)} plot" src="data:image/png;base64,{png}">')
    return "".join(out)


def _discrepancy(d: RunData) -> str:
    disc = d.discrepancy
    if disc is None:
        return ("<h2>Model discrepancy</h2><p class=\"note\">The discrepancy workflow has not been run on this "
                "recording (no results/discrepancy): no effects beyond the model are named.</p>")
    rows = []
    for e in disc.get("effects") or []:
        ps = "; ".join(f"{_e(k)} = " + (f"{fmt_value(p.get('value'), p.get('std'))} ± {fmt_unc(p.get('std'))} "
                                        f"{_e(p.get('unit', ''))}" if p.get("identifiable", True)
                                        and p.get("value") is not None
                                        else f"not identifiable: {_e(p.get('reason', ''))}")
                       for k, p in (e.get("params") or {}).items())
        rows.append([f"<b>{_e(e.get('name'))}</b>", ps, _num(fmt_unc(e.get("gap_after")), e.get("gap_after")),
                     _e(e.get("evidence", ""))])
    floor = disc.get("noise_floor_V")
    out = ["<h2>Model discrepancy: named effects</h2>",
           f"<p>Gap (RMS force residual) of the base model {fmt_unc(disc.get('base_gap'))} V → final model "
           f"{fmt_unc(disc.get('final_gap'))} V" + (f"; noise floor {fmt_unc(floor)} V" if floor is not None else "")
           + ".</p>"]
    out.append(_table(["effect", "parameters (value ± u, k = 1)", "gap after (V)", "evidence"], rows)
               if rows else "<p>No catalogue effect was named.</p>")
    for key, title in (("parameters_before", "before"), ("parameters_after", "after")):
        if disc.get(key):
            out.append(f"<h3>Transducer parameters {title} the effects</h3>"
                       + _table(PARAM_HEADERS, _param_rows(estimates_from_dict(disc[key]), f"disc.{title}.")))
    ties = disc.get("ties") or []
    if ties:
        trows = []
        for t in ties:
            for c in t.get("candidates") or []:
                kf, bf = c.get("k_f") or {}, c.get("b_f") or {}
                trows.append([_e(t.get("kind", "tie")), _e(" + ".join(c.get("effects") or []) or "base model"),
                              f"{fmt_value(kf.get('value'), kf.get('std'))} ± {fmt_unc(kf.get('std'))}",
                              f"{fmt_value(bf.get('value'), bf.get('std'))} ± {fmt_unc(bf.get('std'))}",
                              _num(fmt_unc(c.get("chi2")), c.get("chi2"))])
        out.append("<h3>Ties: explanations the data do not decide between</h3>"
                   "<p>k_f and b_f after the effects are averaged over these models and carry their spread.</p>"
                   + _table(["kind", "model", "k_f (N/m)", "b_f (N*s/m)", "chi2"], trows)
                   + "<ul>" + "".join(f"<li>{_e(t.get('message', ''))}</li>" for t in ties) + "</ul>")
    unexplained = disc.get("unexplained") or []
    out.append("<h3>Unexplained</h3>" + ("<ul>" + "".join(f"<li>{_e(u)}</li>" for u in unexplained) + "</ul>"
                                         if unexplained else "<p>nothing left unexplained</p>"))
    return "".join(out)


def _campaign(d: RunData) -> str:
    from station.report.campaign import campaign_section  # imports this module's helpers

    return campaign_section(d)


def render_report(recording_path: Path) -> str:
    """The complete HTML page of a recording's calibration (see module docstring)."""
    path = Path(recording_path)
    d = load_run(path)
    now = datetime.now(UTC).isoformat(timespec="seconds")
    title = f"Calibration report: {d.rec.transducer_id}, run {d.rec.run_id}"
    body = [f"<h1>{_e(title)}</h1>",
            f'<p class="note">Generated {now} by sinecal {_e(__version__)} from {_e(path.name)}. '
            "u: standard uncertainty (k = 1); U = 2u: expanded uncertainty (k = 2, about 95 % coverage for "
            "a normal distribution). The uncertainties are those of the identification (measurement noise "
            "propagated through the fit); masses and the displacement sensor's calibration are taken as "
            "exact.</p>",
            _conditions(d), _model(d), _parameters(d), _campaign(d), _sensitivity(d), _discrepancy(d), _plots(path)]
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{_e(title)}</title>'
            f"<style>{CSS}</style></head><body>{''.join(body)}</body></html>\n")
