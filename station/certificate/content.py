"""What a calibration certificate states (ISO/IEC 17025 section 7.8), gathered from a recording and
what is stored beside it; the template (``templates/certificate.html.j2``) only lays it out.

Sources (docs/certificate.md): the laboratory, customer, place and reference standards from the
``certificate`` section of the configuration the recording holds; the item from the recording (the
transducer's id, capacity and nominal sensitivity); the method, results, budget and assumptions from
the stored identification (``station.report.data.load_run``, never a new fit); the environmental
conditions from the start document; the uncertainty statement from the budget
(``station.report.statement``); k and the coverage probability from the budget's effective degrees
of freedom (``station.ident.coverage``).  ``Approval`` carries the numbering and the signatures.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from station.certificate.certified import Certified, certified_of
from station.certificate.item import CalibratedItem, calibrated_item, item_budget, scaled_determined
from station.certificate.present import QUANTITY, SYMBOL, plain, typeset, unit_text, value_and_uncertainties
from station.certificate.sdyn import chain_of, sdyn_points
from station.certificate.validity import validity
from station.config import CertificateConfig, MeasurementChain
from station.ident.coverage import K2_PROBABILITY, coverage, coverages
from station.ident.inputs import DEFAULT_END_MASS_REL_STD
from station.ident.models import make_model
from station.ident.names import METHOD_DESCRIPTIONS
from station.ident.result import Check, Estimate
from station.ident.uncertainty import Covariance, ParameterBudget, UncertaintyBudget
from station.lab.traceability import use_text
from station.recording import start_metadata
from station.report.data import ModelCurve, RunData, load_run
from station.report.html import MODELS
from station.report.quantities import fmt_unc, model_sensitivity, range_text, structure_sentence
from station.report.statement import uncertainty_statement

CITATION = ("[1] J. Lu, \u201cSystem identification of force transducers for dynamic measurements using particle "
            "swarm optimization\u201d, Journal of Vibroengineering, vol. 19, no. 2, pp. 864\u2013877, 2017, "
            "https://doi.org/10.21595/jve.2017.17744")
RELATES_ONLY = ("The results relate only to the item calibrated, as received, under the conditions stated. "
                "This certificate shall not be reproduced except in full without the laboratory's written "
                "approval.")
NOT_STATED = ("withheld", "not certified")


@dataclass(frozen=True)
class Approval:
    """The certificate's state: 'draft' | 'issued'; number (None for a draft); who prepared it and
    who approved and issued it (name, role), when (ISO 8601 UTC); the certificate it replaces."""

    status: str = "draft"
    number: str | None = None
    prepared_by: str = ""
    approved_by: str = ""
    approver_role: str = ""
    issued_at: str = ""
    replaces: str | None = None
    reason: str = ""


def _cert_config(d: RunData) -> CertificateConfig:
    cfg = d.rec.config if isinstance(d.rec.config, dict) else {}
    return CertificateConfig.model_validate(cfg.get("certificate") or {})


def _environment(d: RunData) -> dict[str, Any] | None:
    env = start_metadata(d.rec.documents).get("environment")
    return env if isinstance(env, dict) else None


def _result(name: str, value: float | None, budget_entry: dict[str, Any] | None, unit: str,
            status: str = "certified", note: str = "") -> dict[str, Any]:
    """One row of the results: the value with u, k, U and p (the certificate's k = 2 convention),
    its status ('certified' | 'conditional' | 'poorly determined' | 'withheld' | 'not certified')
    and the note that says why, in words."""
    base = {"name": name, "symbol": SYMBOL.get(name, name), "meaning": QUANTITY.get(name, name),
            "unit": unit, "unit_text": unit_text(unit), "status": status, "note": typeset(note), "determined": False}
    if value is not None and status not in NOT_STATED and (budget_entry is None
                                                         or budget_entry.get("combined") is None):
        status, base["note"] = "not certified", "not certified: no uncertainty budget is stored for it"
    if value is None or budget_entry is None or budget_entry.get("combined") is None or status in NOT_STATED:
        return {**base, "value": None, "text": "not certified" if status == "not certified" else "withheld",
                "u": None, "k": None, "p": None, "U": None, "nu_eff": None, "u_text": "", "U_text": "",
                "k_text": "", "status": status if status in NOT_STATED else "withheld"}
    c = coverage(ParameterBudget.from_dict(budget_entry), k2=True)
    text, U_text, u_text = value_and_uncertainties(value, c.U, c.u)
    return {**base, "value": value, "u": c.u, "k": c.k, "p": c.p, "U": c.U,
            "nu_eff": None if math.isinf(c.nu_eff) else c.nu_eff,
            "text": text, "u_text": u_text, "U_text": U_text, "k_text": f"{c.k:.3g}"}


def _status(p: Estimate, structure: dict[str, Any] | None) -> tuple[str, str]:
    """(status, note) of an identified parameter from identify's flags: withheld (not identifiable),
    not certified (conditional on an assumption the data contradict), conditional, poorly determined."""
    if not p.identifiable:
        reason = p.reason.removeprefix("withheld: ")
        return "withheld", f"withheld: {reason}" if reason else "withheld: the data do not determine it"
    contradicted = bool(((structure or {}).get("coupling") or {}).get("contradicted_by_the_data"))
    if p.flag == "conditional" and contradicted and "contradict" in p.reason:
        return "not certified", ("not certified: it rests on an assumption the data contradict (" + p.reason + ")")
    if p.flag == "conditional":
        return "conditional", "conditional: " + (p.reason or "on an assumed input stated below")
    if p.flag == "poorly_determined":
        return "poorly determined", ("poorly determined: its relative uncertainty is above the station's policy"
                                     + (f" ({p.reason})" if p.reason else ""))
    return "certified", p.reason


def end_mass_statement(ident: Certified, budget: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """What the certificate says of the end mass m_e: determined by a campaign (value, u, its
    correlation with S), or assumed (its value, source, standard uncertainty, share of u²(S)) with the
    campaign named as the way to remove it."""
    a = ident.assumptions.get("end_mass_kg") or {}
    me = ident.parameters.get("m_e")
    if ident.kind == "campaign" and me is not None and me.value is not None and me.std:
        c = ident.covariance
        r = None
        if c is not None and "S" in c.names and "m_e" in c.names:
            m = c.array
            i, j = c.names.index("S"), c.names.index("m_e")
            r = float(m[i, j] / math.sqrt(m[i, i] * m[j, j])) if m[i, i] > 0 and m[j, j] > 0 else None
        U = 2.0 * me.std
        v_text, U_text = value_and_uncertainties(me.value, U)
        masses = ", ".join(f"{plain(x.get('load_mass_kg'), 5)} kg" for x in ident.runs)
        return {"status": "determined", "value": me.value, "std": me.std, "source": "campaign", "share_of_u2_S": None,
                "correlation_with_S": r, "runs": ident.runs,
                "text": (f"The end mass m_e is determined by the data: a campaign of {len(ident.runs)} runs of this "
                         f"transducer with the load masses {masses} gives m_e = {v_text} kg, U = {U_text} kg (k = 2)"
                         + (f", correlated with S (correlation coefficient {r:.2f}; the covariance is stated below)"
                            if r is not None else "")
                         + ". S, k_f and b_f are determined jointly with it; no end mass is assumed.")}
    s = budget.get("S") or {}
    u_e = (s.get("contributions") or {}).get("end_mass")
    uc = s.get("combined")
    share = (float(u_e) ** 2 / float(uc) ** 2) if isinstance(u_e, int | float) and uc else None
    source = str(a.get("source", ""))
    std = a.get("std")
    where = {"config": "the transducer's data as configured (transducer.end_mass_kg)",
             "recording": "the run's import (RUN.yaml end_mass_kg)",
             "assumed": "an assumed value"}.get(source, source or "not stated")
    default = isinstance(std, int | float) and isinstance(a.get("value"), int | float) and a["value"] and math.isclose(
        float(std), DEFAULT_END_MASS_REL_STD * float(a["value"]), rel_tol=1e-9)
    return {"status": "assumed", "value": a.get("value"), "std": std, "source": source, "source_text": where,
            "std_is_default": bool(default), "share_of_u2_S": share,
            "text": (f"The end mass m_e is not determined by this run: it is assumed, {plain(a.get('value'), 4)} kg "
                     f"from {where}"
                     + (f", standard uncertainty {fmt_unc(float(std))} kg"
                        + (f" (the station's default of {100 * DEFAULT_END_MASS_REL_STD:g} % of the value, "
                           "not supported by a certificate)" if default else "")
                        if isinstance(std, int | float) else ", without an uncertainty: S, k_f and b_f are "
                        "conditional on it")
                     + (f". It makes {100 * share:.0f} % of u²(S)." if share is not None else ".")
                     + " A campaign of runs with several top masses on the same transducer (station campaign, "
                       "POST /campaigns) determines m_e from the data and removes this assumption.")}


def result_text(ident: Certified) -> str:
    """Which stored result the certificate states, in words (no internal names)."""
    how = METHOD_DESCRIPTIONS.get(ident.method, ident.method).split(" (")[0].replace("the paper's", "[1]'s")
    written = ident.source.rsplit("written ", 1)[-1].rstrip(")") if "written " in ident.source else ""
    what = ("the joint identification of the campaign's runs" if ident.kind == "campaign"
            else "the run's identification" if written else "an identification computed for this certificate "
            "(none is stored with the recording)")
    return f"{what} ({how}){', stored ' + written if written else ''}"


def model_grid(d: RunData, ident: Certified, item: CalibratedItem, f_lo: float, f_hi: float
               ) -> dict[str, Any] | None:
    """The model's S_dyn on a grid within the plan's range only (never extrapolated), in the item's
    unit, with u from the stated covariance (and the conditioner's gain); None when no model is drawn."""
    curve = d.curve
    if ident.kind == "campaign":
        p, cov = ident.parameters, ident.covariance
        names = ("S", "k_f", "b_f")
        m_e = p["m_e"].value
        m_l = (ident.assumptions.get("load_mass_kg") or {}).get("value")
        if cov is None or m_e is None or m_l is None or any(p[n].value is None for n in names):
            return None
        i = [cov.names.index(n) for n in names]
        theta = np.array([float(p[n].value or 0.0) for n in names])
        curve = ModelCurve(make_model("sdof", float(m_e), float(m_l)), theta, cov.array[np.ix_(i, i)])
    if curve is None:
        return None
    ff = np.geomspace(f_lo, f_hi, 120) if f_hi > f_lo else np.array([f_lo])
    mag, u_mag, ph, u_ph = model_sensitivity(curve, ff)
    mag = item.scale * mag
    u = None if u_mag is None else np.hypot(item.scale * u_mag, mag * item.rel_std)
    return {"f_hz": ff.tolist(), "magnitude": mag.tolist(), "u_magnitude": None if u is None else u.tolist(),
            "phase_rad": ph.tolist(), "u_phase_rad": None if u_ph is None else u_ph.tolist()}


def correlation(cov: Covariance | None) -> dict[str, Any] | None:
    """The parameters' correlation matrix (names, symbols, rows of text to two decimals) or None."""
    if cov is None or not cov.names:
        return None
    m = cov.array
    d = [math.sqrt(m[i, i]) if m[i, i] > 0 else 0.0 for i in range(len(cov.names))]
    rows = [[f"{m[i, j] / (d[i] * d[j]):.2f}" if d[i] and d[j] else "—" for j in range(len(d))] for i in range(len(d))]
    return {"names": list(cov.names), "symbols": [SYMBOL.get(n, n) for n in cov.names], "rows": rows,
            "matrix": [list(r) for r in cov.matrix], "units": list(cov.units)}


CHAIN_TEXT = {"gain_rel_std": ("gain ratio of the force and displacement chains, relative", ""),
              "flatness_rel_std": ("gain flatness from step to step, relative", ""),
              "phase_offset_std_deg": ("phase offset between the channels", "°"),
              "phase_std_deg": ("phase error from step to step", "°"),
              "delay_std_s": ("time skew between the channels", "s"),
              "displacement_resonance_hz": ("displacement sensor resonance", "Hz"),
              "displacement_resonance_std_hz": ("its standard uncertainty", "Hz"),
              "displacement_damping": ("its damping ratio", ""),
              "displacement_damping_std": ("its standard uncertainty", "")}


def chain_lines(stated: dict[str, Any]) -> list[str]:
    """The measurement chain's standard uncertainties in words, each a default of the station (no
    certificate behind it) marked as such."""
    defaults = MeasurementChain().model_dump()
    out = []
    for key, v in stated.items():
        if v is None or key not in CHAIN_TEXT or (key.startswith("displacement_damping")
                                                  and stated.get("displacement_resonance_hz") is None):
            continue
        text, unit = CHAIN_TEXT[key]
        out.append(f"{text}: u = {typeset(f'{v:g}')}{' ' + unit if unit else ''}"
                   + (" (the station's default, not from a certificate)" if v == defaults.get(key) else ""))
    return out


def warnings_of(checks: tuple[Check, ...] | list[Check]) -> list[dict[str, Any]]:
    """identify's findings the certificate prints (warnings and refusals; info notes are left out)."""
    return [{"name": c.name, "severity": c.severity, "message": typeset(c.message),
             "step": c.step} for c in checks if c.severity != "info"]


def register_standards(standards: list[dict[str, Any]], load_mass_kg: float = 0.0,
                       reference_conditioner: bool = False) -> list[dict[str, Any]]:
    """The lab register's records of the run's reference standards (``station.lab.register.Standard``
    as the run stored them) in the certificate's form, with what each does in the budget."""
    return [{"budget": use_text(s, load_mass_kg, reference_conditioner), "recorded": True,
             "name": s.get("description") or f"{s.get('kind', 'standard')} {s.get('id', '')}",
             "kind": str(s.get("kind", "")), "id": str(s.get("id", "")),
             "certificate_id": str(s.get("certificate_id", "")), "due_date": str(s.get("due_date", "")),
             "traceability": "; ".join(x for x in (f"certificate issued by {s['issuer']}" if s.get("issuer") else "",
                                                   f"u = {s['uncertainty']:g} {s.get('uncertainty_unit', '')}"
                                                   if isinstance(s.get("uncertainty"), int | float) else "") if x)}
            for s in standards]


def certificate_content(path: str | Path, approval: Approval | None = None,
                        register: dict[str, Any] | None = None) -> dict[str, Any]:
    """Everything the certificate states, as plain data (JSON-able): the input of the HTML template,
    the DCC and the content hash of an issued certificate.  register: the lab register's records as
    the run used them (``{"transducer": {...}, "standards": [...]}``; the daemon's runs carry them),
    which take the place of the configuration's standards and add the item's type, serial and owner."""
    d = load_run(path)
    approval = approval or Approval()
    cc = _cert_config(d)
    rec, ident = d.rec, certified_of(d)
    cfg = rec.config if isinstance(rec.config, dict) else {}
    item = calibrated_item(cfg)
    values = {n: p.value for n, p in ident.parameters.items()}
    budget_item = item_budget(ident.budget, values, item)
    typed_budget = UncertaintyBudget.from_dict(budget_item)
    structure = ident.assumptions.get("structure")
    st_struct = structure if isinstance(structure, dict) else None
    findings = warnings_of(ident.checks)
    results = []
    for name, p in ident.parameters.items():
        status, note = _status(p, structure if isinstance(structure, dict) else None)
        unit = item.unit if name == "S" else p.unit
        value = None if p.value is None else (item.scale if name == "S" else 1.0) * p.value
        results.append(_result(name, value, budget_item.get(name), unit, status, note))
    for name, raw in ident.determined.items():
        q = scaled_determined(raw, name, item)
        if "range" in q or q.get("value") is None or q.get("combined") is None:
            continue
        entry = {"contributions": {k: v for k, v in q.items() if k not in ("value", "unit", "combined", "note")
                                   and (v is None or isinstance(v, int | float))},
                 "combined": q["combined"], "dof": (ident.budget.get("k_f") or {}).get("dof")}
        results.append({**_result(name, float(q["value"]), entry, str(q.get("unit", "")),
                                  note=str(q.get("note", ""))), "determined": True})
    r = d.response
    u_m = ident.mass_std_kg
    pts = sdyn_points(r.f_hz, r.H, r.cov, ident.mass_kg, u_m, chain_of(ident.assumptions), item.scale, item.rel_std)
    u_mag, u_ph = pts.u_magnitude, pts.u_phase_rad
    response = []
    for i, f in enumerate(pts.f_hz):
        c_mag = coverage(ParameterBudget.of({"all": float(u_mag[i])}, float(u_mag[i]), ""), k2=True)
        mag_text, U_text = value_and_uncertainties(float(pts.magnitude[i]), c_mag.k * float(u_mag[i]))
        ph_deg, U_ph = math.degrees(float(pts.phase_rad[i])), math.degrees(c_mag.k * float(u_ph[i]))
        ph_text, U_ph_text = value_and_uncertainties(ph_deg, U_ph)
        response.append({"f_hz": float(f), "magnitude": float(pts.magnitude[i]), "u_magnitude": float(u_mag[i]),
                         "U_magnitude": c_mag.k * float(u_mag[i]), "phase_deg": ph_deg, "U_phase_deg": U_ph,
                         "text": mag_text, "U_text": U_text, "phase_text": ph_text, "U_phase_text": U_ph_text,
                         "terms": {k: float(v[i]) for k, v in pts.mag_terms.items()},
                         "phase_terms_rad": {k: float(v[i]) for k, v in pts.phase_terms.items()}})
    radius = {st.index: st.crank_radius_m for st in rec.steps}
    valid = validity([float(f) for f in pts.f_hz], [radius.get(i, 0.0) for i in r.step_index], ident.mass_kg,
                     st_struct)
    k_points = 2.0  # every point's sources are Type B or rest on thousands of samples: nu_eff infinite
    masses = []
    for key, label in (("end_mass_kg", "end mass m_e"), ("load_mass_kg", "load mass m_l")):
        a = ident.assumptions.get(key) or {}
        masses.append({"name": label, "value": a.get("value"), "std": a.get("std"), "source": a.get("source", "")})
    st = structure if isinstance(structure, dict) else None
    budget_sources = list(next(iter(budget_item.values()))["contributions"]) if budget_item else []
    budget = [{"name": n, "quantity": QUANTITY.get(n, n), "unit": unit_text(b.get("unit", "")),
               "cells": [typeset(fmt_unc(b["contributions"].get(s))) if b["contributions"].get(s) is not None
                         else "conditional" for s in budget_sources], "combined": typeset(fmt_unc(b.get("combined")))}
              for n, b in budget_item.items()]
    tr_cfg = cfg.get("transducer")
    tr: dict[str, Any] = tr_cfg if isinstance(tr_cfg, dict) else {}
    reg = register or {}
    reg_tr = reg.get("transducer") if isinstance(reg.get("transducer"), dict) else {}
    assert isinstance(reg_tr, dict)
    unrecorded = "not recorded with the run: listed from the configuration (certificate.standards)"
    standards = register_standards(reg["standards"], rec.load_mass_kg, item.kind == "transducer") if reg.get(
        "standards") else [{**s.model_dump(), "recorded": False, "budget": unrecorded} for s in cc.standards]
    return {
        "approval": asdict(approval),
        "laboratory": cc.laboratory.model_dump(), "customer": None if cc.customer is None else cc.customer.model_dump(),
        "place": cc.place,
        "title": item.title, "calibrated": item.to_dict(),
        "item": {"transducer_id": rec.transducer_id, "capacity_N": rec.capacity_N, "text": item.text,
                 "nominal_sensitivity_V_per_N": tr.get("sensitivity_V_per_N"),
                 "signal_sensitivity_V_per_N": rec.sensitivity_V_per_N,
                 **{k: str(reg_tr.get(k) or "") for k in ("type", "serial", "owner")}},
        "run": {"run_id": rec.run_id, "recording": Path(path).name, "start_time": rec.start_time,
                "end_time": rec.end_time, "exit_status": rec.exit_status, "source": rec.source,
                "software_version": rec.software_version,
                "steps": [{"f_hz": s.crank_frequency_hz, "radius_mm": 1e3 * s.crank_radius_m} for s in rec.steps]},
        "method": {"name": "dynamic calibration by stepped sine excitation on a crank (sine-mechanism) rig",
                   "estimator": ident.method, "estimator_text": METHOD_DESCRIPTIONS.get(ident.method, ""),
                   "model": ident.model,
                   "model_text": typeset(MODELS.get(ident.model, "").replace("paper Eq.", "[1] Eq.")
                                         .replace("the paper's", "[1]'s")),
                   "result": ident.source, "result_text": result_text(ident), "reference": CITATION,
                   "campaign": ident.runs},
        "environment": _environment(d),
        "standards": standards, "standards_source": "register" if reg.get("standards") else "configuration",
        "results": results, "response": response, "response_k": k_points, "response_p": K2_PROBABILITY,
        "response_unit": item.unit, "response_unit_text": unit_text(item.unit),
        "end_mass": end_mass_statement(ident, budget_item),
        "budget": {"sources": budget_sources, "rows": budget},
        "coverage": {n: c.to_dict() for n, c in coverages(typed_budget, k2=True).items()},
        "statement": [typeset(x) for x in uncertainty_statement(typed_budget, ident.assumptions, k2=True)],
        "correlation": correlation(ident.covariance),
        "validity": valid,
        "bode_model": model_grid(d, ident, item, valid["f_min_hz"], valid["f_max_hz"]),
        "assumptions": {"masses": masses, "M_kg": ident.mass_kg, "u_M_kg": u_m,
                        "structure": typeset(structure_sentence(st)) if st else "",
                        "chain": chain_lines(ident.assumptions.get("measurement_chain") or {}),
                        "ranges": [{"name": k, "quantity": QUANTITY.get(k, k), "range": typeset(range_text(v["range"])),
                                    "unit": unit_text(v.get("unit", "")),
                                    "conditional_on": typeset(v.get("conditional_on", ""))}
                                   for k, v in ident.determined.items() if "range" in v]},
        "checks": findings,
        "relates_only": RELATES_ONLY,
    }
