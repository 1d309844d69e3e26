"""The calibration report of a run as one self-contained HTML page (Jinja2 template report.html.j2 of
station/report/templates, the certificates' engine; plots embedded as base64 PNG,
styles inline, no external assets).  Layout and definitions: docs/report.md."""

from __future__ import annotations

import base64
import logging
import math
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from markupsafe import Markup

from station import __version__
from station.errors import StationError
from station.ident.coverage import coverages
from station.ident.montecarlo import check_result
from station.ident.names import METHOD_DESCRIPTIONS
from station.ident.response.frf import FrequencyResponse
from station.ident.result import IdentificationResult, estimates_from_dict
from station.report.campaign import campaign_section
from station.report.data import RunData, load_run
from station.report.plots import PLOT_NAMES, render_plot
from station.report.quantities import (
    COVERAGE_K,
    fmt_unc,
    fmt_value,
    measured_sensitivity,
    model_sensitivity,
    range_text,
    structure_sentence,
)
from station.report.render import render_template
from station.report.statement import uncertainty_statement
from station.report.tables import PARAM_HEADERS, budget_table, esc, num, param_rows, table
from station.run.methods import METHODS_RESULT, MethodOutcome, agreement

log = logging.getLogger(__name__)
MODELS = {
    "sdof": "stiff coupling, paper Eq. 9: H(s) = −S·M·k_f / (M s² + b_f s + k_f), M = m_e + m_l",
    "coupled": "finite coupling stiffness k_c and damping b_c, paper Eq. 8 (fourth order)",
    "h2": "the paper's digital Eq. 11 (bilinear transform of Eq. 9), mapped to S, k_f, b_f with the known masses",
    "h1": "the paper's digital Eq. 10 (bilinear transform of Eq. 8), mapped with the known masses",
}
CSS = """body{font-family:sans-serif;max-width:1000px;margin:2em auto;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.2em}td,th{border:1px solid #bbb;padding:3px 8px;text-align:left}
th{background:#eee}td.num{text-align:right;font-family:monospace}.na{color:#a33}.note{color:#555;font-size:90%}
img{max-width:100%;border:1px solid #ddd;margin:.5em 0}h2{border-bottom:2px solid #ccc;padding-bottom:2px}
@page{size:A4 landscape;margin:12mm}
@media print{body{max-width:none;margin:0;font-size:8pt}table{width:100%;table-layout:auto}
td,th{padding:1px 3px;overflow-wrap:anywhere}td.num{white-space:nowrap}img{max-width:100%;page-break-inside:avoid}
tr{page-break-inside:avoid}}"""


def _conditions(d: RunData) -> str:
    rec = d.rec
    cfg = rec.config if isinstance(rec.config, dict) else {}
    rig, tr, cond = ((v if isinstance(v, dict) else {}) for v in (cfg.get(k) for k in ("rig", "transducer",
                                                                                       "conditioner")))
    top = rig.get("top_mass_kg")  # an imported run's RUN.yaml has only top_mass_kg = the load mass
    lost = rec.lost_samples
    rows = [["transducer id", esc(rec.transducer_id)],
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
            ["source", esc(rec.source)],
            ["run id", esc(rec.run_id)],
            ["start / end (UTC)", f"{esc(rec.start_time)} / {esc(rec.end_time or '-')}"],
            ["exit status", esc(rec.exit_status + (f" ({rec.reason})" if rec.reason else ""))],
            ["lost samples", f"{int(lost[:, 1].sum()) if lost.size else 0} in {len(lost)} gap(s)"],
            ["software version (recording / report)", f"{esc(rec.software_version or '?')} / {esc(__version__)}"]]
    steps = [[str(s.index), num(f"{s.crank_frequency_hz:g}", s.crank_frequency_hz),
              num(f"{1e3 * s.crank_radius_m:g}", s.crank_radius_m),
              num(f"{(s.end_sample - s.start_sample) / rec.sample_rate_hz:g}"), num(str(s.lost_in_window)),
              "yes" if s.usable else '<span class="na">no: samples lost in the window</span>']
             for s in rec.steps]
    return ("<h2>Transducer and run conditions</h2>" + table(["", ""], rows)
            + "<h3>Steps</h3>" + table(["step", "crank frequency (Hz)", "crank radius (mm)", "record window (s)",
                                         "lost samples in window", "used"], steps))


def _model(d: RunData) -> str:
    ident = d.ident
    fit = ident.fit
    rms = ", ".join(fmt_unc(v) for v in fit.residual_rms_V)
    rows = [["method", f"{esc(ident.method)}: {esc(METHOD_DESCRIPTIONS.get(ident.method, ''))}"],
            ["model", f"{esc(ident.model)}: {esc(MODELS.get(ident.model, ''))}"],
            ["result", esc(d.ident_source)],
            ["masses used", f"M = m_e + m_l = {d.mass_kg:g} kg"],
            ["fit", f"MSE {fmt_unc(fit.mse)} V², residual RMS per step [{rms}] V, "
                    f"χ²/dof {fmt_unc(fit.chi2_per_dof)}, {fit.n_points or '?'} points"],
            ["condition number", fmt_unc(None if ident.identifiability is None
                                         else ident.identifiability.condition_number)]]
    for name, a in ident.assumptions.items():
        if isinstance(a, dict) and "source" in a:
            rows.append([esc(name), f"{a.get('value')} ({esc(a['source'])}"
                         + (f", u = {fmt_unc(a['std'])})" if a.get("std") is not None
                            else "; no uncertainty: the results are conditional on it)")])
    st = ident.assumptions.get("structure")
    if st:
        rows.append(["model structure", esc(structure_sentence(st))])
    notes = "".join(f"<li>{esc(n)}</li>" for n in ident.notes)
    checks = "".join(f'<li data-check="{esc(c.name)}">{esc(c.severity)}: {esc(c.name)}'
                     f'{"" if c.step is None else " (step " + str(c.step) + ")"}: {esc(c.message)}</li>'
                     for c in ident.checks)
    det = [[esc(k), num(fmt_value(v.get("value"), v.get("combined")), v.get("value")), num(fmt_unc(v.get("combined"))),
            esc(v.get("unit", ""))] if "range" not in v else
           [esc(k), esc(range_text(v["range"])), esc(v.get("conditional_on", "")), esc(v.get("unit", ""))]
           for k, v in ident.determined.items()]
    return ("<h2>Model and identification</h2>" + table(["", ""], rows)
            + (f'<h3>Input checks</h3><ul class="note">{checks}</ul>' if checks else "")
            + (("<h3>What the data determine whatever the end mass and the coupling</h3>"
                + table(["quantity", "value", "u (k = 1)", "unit"], det)) if det else "")
            + (f'<ul class="note">{notes}</ul>' if notes else ""))


def _budget(d: RunData) -> str:
    """GUM budget: standard uncertainty of each parameter per source (k = 1), and combined."""
    return budget_table(d.ident.budget, "budget.")


def _parameters(d: RunData) -> str:
    ks = {n: c.k for n, c in coverages(d.ident.budget).items()}
    return ("<h2>Identified parameters</h2>" + table(PARAM_HEADERS, param_rows(d.ident.parameters,
                                                                                 "param.", ks), "params")
            + _budget(d))


def _statement(d: RunData) -> str:
    sentences = uncertainty_statement(d.ident.budget, d.ident.assumptions)
    return ('<h2>Uncertainty statement</h2><ul class="statement">'
            + "".join(f"<li>{esc(s)}</li>" for s in sentences) + "</ul>")


def _monte_carlo(path: Path, d: RunData, trials: int) -> str:
    """GUM Supplement 1 check of the linear budget (station.ident.montecarlo)."""
    if trials <= 0:
        return ""
    try:
        r = d.response
        zero = np.zeros(r.f_hz.size)
        mc = check_result(d.rec, d.ident, frf=FrequencyResponse(r.f_hz, r.H, r.cov, zero, zero), trials=trials, seed=0)
    except StationError as e:
        return f'<h2>Monte Carlo check (GUM Supplement 1)</h2><p class="note">not made: {esc(e)}</p>'
    rows = [[esc(p.name), num(fmt_unc(p.u_linear), p.u_linear), num(fmt_unc(p.u_mc), p.u_mc, f"mc.{p.name}.u"),
             num(f"{p.u_mc / p.u_linear:.3f}"), num(f"{fmt_value(p.y - p.k * p.u_linear, p.u_linear)} … "
                                                  f"{fmt_value(p.y + p.k * p.u_linear, p.u_linear)}"),
             num(f"{fmt_value(p.low, p.u_linear)} … {fmt_value(p.high, p.u_linear)}"),
             num(f"{fmt_unc(p.d_low)} / {fmt_unc(p.d_high)}"), num(fmt_unc(p.delta)),
             "yes" if p.agrees else "no", esc(p.unit)] for p in mc.parameters]
    return ("<h2>Monte Carlo check (GUM Supplement 1)</h2>"
            f'<p class="note">{mc.trials} trials (seed {mc.seed}) drawing {esc(", ".join(mc.sources))} and '
            "refitting each; agreement per GUM S1 8.2: both ends of y ± U within δ (half a unit of u's one "
            f"significant digit) of the Monte Carlo 95 % interval; with {mc.trials} trials the interval's ends "
            f"themselves scatter by about {2.7 / math.sqrt(mc.trials):.2g} u.</p>"
            + table(["parameter", "u linear", "u Monte Carlo", "ratio", "y ± U (linear)", "95 % interval (MC)",
                     "d_low / d_high", "δ", "agrees", "unit"], rows, "montecarlo"))


def mass_std(assumptions: dict) -> float:
    """u(M) of M = m_e + m_l from the result's assumptions (0 for a mass without one)."""
    us = [(assumptions.get(k) or {}).get("std") for k in ("end_mass_kg", "load_mass_kg")]
    return math.hypot(*[float(u) if isinstance(u, int | float) else 0.0 for u in us])


def methods_section(d: RunData) -> str:
    """Every listed identification side by side (``results/methods``): value ± u per parameter, z
    against the primary (difference in units of the combined standard uncertainty), why a method
    withholds a value or gave none; empty for runs identified before methods were listed."""
    listed = d.results.get(METHODS_RESULT)
    outcomes = [MethodOutcome.from_dict(o) for o in (listed.payload.get("methods", []) if listed else [])]
    if not outcomes:
        return ""
    names = list(d.ident.parameters)
    rows = []
    for o in outcomes:
        stored = d.results.get(o.result_name or "") if o.status == "done" else None
        res = IdentificationResult.from_dict(stored.payload) if stored is not None else None
        label = f"{'★ ' if o.primary else ''}{esc(o.method)} ({esc(o.model)}"
        label += f" → {esc(o.result_model)})" if o.result_model and o.result_model != o.model else ")"
        row = [label, esc(o.status)]
        if res is None:
            row.append(f'<td colspan="{len(names)}" class="na" data-key="method.{esc(o.label)}">'
                       f"{esc(o.reason or 'no result')}</td>")
        else:
            agree = {} if o.primary else agreement(d.ident, res)
            for n in names:
                p, a = res.parameters.get(n), agree.get(n)
                if p is None or not p.identifiable or p.value is None:
                    row.append(f'<td class="na" data-key="method.{esc(o.label)}.{esc(n)}">withheld: '
                               f"{esc(p.reason if p else 'not in this model')}</td>")
                    continue
                z = "" if a is None else f" (z = {a['z']:.2f})" if a["z"] is not None else f" (no z: {a['reason']})"
                row.append(f'<td data-key="method.{esc(o.label)}.{esc(n)}" data-value="{p.value!r}">'
                           f"{esc(fmt_value(p.value, p.std))} ± {esc(fmt_unc(p.std))} {esc(p.unit)}{esc(z)}</td>")
        row += [num("n/a" if o.compute_s is None else f"{o.compute_s:.2f}", o.compute_s), esc(o.seed)]
        rows.append(row)
    return ("<h2>Methods side by side</h2><p class=\"note\">Every identification listed for this run; ★ is the "
            "primary, the result of this report. z: the difference from the primary in units of their combined "
            "standard uncertainty sqrt(u² + u_primary²); |z| > 2 is a disagreement. A secondary method's refusal "
            "or failure does not affect the primary result.</p>"
            + table(["method (model)", "status", *[esc(n) for n in names], "time (s)", "seed"], rows, "methods"))


def _sensitivity(d: RunData) -> str:
    r = d.response
    u_m = mass_std(d.ident.assumptions)
    mag, u_mag, ph, u_ph = measured_sensitivity(r.H, r.cov, d.mass_kg, u_m)
    model = model_sensitivity(d.curve, r.f_hz) if d.curve is not None else None
    if model is not None:
        ph = model[2] + np.angle(np.exp(1j * (ph - model[2])))
    rows = []
    for i, f in enumerate(r.f_hz):
        row = [str(r.step_index[i]), num(f"{f:.6g}", f),
               num(fmt_value(mag[i], u_mag[i]), mag[i], f"sdyn.{i}"), num(fmt_unc(u_mag[i])),
               num(fmt_unc(COVERAGE_K * u_mag[i])),
               num(fmt_value(np.degrees(ph[i]), np.degrees(u_ph[i])), np.degrees(ph[i]), f"phase.{i}"),
               num(fmt_unc(np.degrees(u_ph[i]))), num(fmt_unc(COVERAGE_K * np.degrees(u_ph[i])))]
        if model is not None:
            m_mag, m_umag, m_ph, m_uph = model
            row += [num(fmt_value(m_mag[i], None if m_umag is None else m_umag[i]), m_mag[i]),
                    num("n/a" if m_umag is None else fmt_unc(COVERAGE_K * m_umag[i])),
                    num(fmt_value(np.degrees(m_ph[i]), None if m_uph is None else np.degrees(m_uph[i]))),
                    num("n/a" if m_uph is None else fmt_unc(COVERAGE_K * np.degrees(m_uph[i])))]
        rows.append(row)
    head = ["step", "f (Hz)", "|S_dyn| (V/N)", "u (V/N)", "U, k = 2 (V/N)", "phase (°)", "u (°)", "U, k = 2 (°)"]
    if model is not None:
        head += ["model |S_dyn| (V/N)", "model U, k = 2 (V/N)", "model phase (°)", "model U, k = 2 (°)"]
    note = (f"S_dyn(f) = −H(f)/M with M = {d.mass_kg:g} kg (u(M) = {u_m:.2g} kg, in the points' u): force signal "
            f"per inertial force of the moving masses. Measured points from {r.source}.")
    extra = d.curve.note if d.curve is not None else d.curve_note
    if extra:
        note += f" {extra[0].upper()}{extra[1:]}."
    return ("<h2>Dynamic sensitivity and phase versus frequency</h2>" + table(head, rows, "sdyn")
            + f'<p class="note">{esc(note)}</p>')


def _plots(path: Path) -> str:
    out = ["<h2>Plots</h2>"]
    for name in PLOT_NAMES:
        png = base64.b64encode(render_plot(path, name)).decode("ascii")
        out.append(f'<h3>{esc(name)}</h3><img alt="{esc(name)} plot" src="data:image/png;base64,{png}">')
    return "".join(out)


def _discrepancy(d: RunData) -> str:
    disc = d.discrepancy
    if disc is None:
        return ("<h2>Model discrepancy</h2><p class=\"note\">The discrepancy workflow has not been run on this "
                "recording (no results/discrepancy): no effects beyond the model are named.</p>")
    rows = []
    for e in disc.get("effects") or []:
        ps = "; ".join(f"{esc(k)} = " + (f"{fmt_value(p.get('value'), p.get('std'))} ± {fmt_unc(p.get('std'))} "
                                        f"{esc(p.get('unit', ''))}" if p.get("identifiable", True)
                                        and p.get("value") is not None
                                        else f"not identifiable: {esc(p.get('reason', ''))}")
                       for k, p in (e.get("params") or {}).items())
        rows.append([f"<b>{esc(e.get('name'))}</b>", ps, num(fmt_unc(e.get("gap_after")), e.get("gap_after")),
                     esc(e.get("evidence", ""))])
    floor = disc.get("noise_floor_V")
    out = ["<h2>Model discrepancy: named effects</h2>",
           f"<p>Gap (RMS force residual) of the base model {fmt_unc(disc.get('base_gap'))} V → final model "
           f"{fmt_unc(disc.get('final_gap'))} V" + (f"; noise floor {fmt_unc(floor)} V" if floor is not None else "")
           + ".</p>"]
    out.append(table(["effect", "parameters (value ± u, k = 1)", "gap after (V)", "evidence"], rows)
               if rows else "<p>No catalogue effect was named.</p>")
    for key, title in (("parameters_before", "before"), ("parameters_after", "after")):
        if disc.get(key):
            out.append(f"<h3>Transducer parameters {title} the effects</h3>"
                       + table(PARAM_HEADERS, param_rows(estimates_from_dict(disc[key]), f"disc.{title}.")))
    ties = disc.get("ties") or []
    if ties:
        trows = []
        for t in ties:
            for c in t.get("candidates") or []:
                kf, bf = c.get("k_f") or {}, c.get("b_f") or {}
                trows.append([esc(t.get("kind", "tie")), esc(" + ".join(c.get("effects") or []) or "base model"),
                              f"{fmt_value(kf.get('value'), kf.get('std'))} ± {fmt_unc(kf.get('std'))}",
                              f"{fmt_value(bf.get('value'), bf.get('std'))} ± {fmt_unc(bf.get('std'))}",
                              num(fmt_unc(c.get("chi2")), c.get("chi2"))])
        out.append("<h3>Ties: explanations the data do not decide between</h3>"
                   "<p>k_f and b_f after the effects are averaged over these models and carry their spread.</p>"
                   + table(["kind", "model", "k_f (N/m)", "b_f (N*s/m)", "chi2"], trows)
                   + "<ul>" + "".join(f"<li>{esc(t.get('message', ''))}</li>" for t in ties) + "</ul>")
    unexplained = disc.get("unexplained") or []
    out.append("<h3>Unexplained</h3>" + ("<ul>" + "".join(f"<li>{esc(u)}</li>" for u in unexplained) + "</ul>"
                                         if unexplained else "<p>nothing left unexplained</p>"))
    return "".join(out)


def render_report(recording_path: Path, monte_carlo: int = 0) -> str:
    """The complete HTML page of a recording's calibration (see module docstring); monte_carlo > 0
    adds the GUM Supplement 1 check of the budget with that many trials (refits: about 3 ms each)."""
    path = Path(recording_path)
    d = load_run(path)
    now = datetime.now(UTC).isoformat(timespec="seconds")
    title = f"Calibration report: {d.rec.transducer_id}, run {d.rec.run_id}"
    sections = [_statement(d), _conditions(d), _model(d), _parameters(d), _monte_carlo(path, d, monte_carlo),
                methods_section(d), campaign_section(d), _sensitivity(d), _discrepancy(d), _plots(path)]
    # the page skeleton is a template (report/templates, station.report.render); the
    # sections are HTML built (and escaped) here
    return render_template("station.report", "report.html.j2", title=title, css=Markup(CSS), generated=now,
                           version=__version__, source=path.name, sections=sections) + "\n"
