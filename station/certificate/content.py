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

from station.config import CertificateConfig
from station.ident.coverage import coverage, coverages
from station.recording import start_metadata
from station.report.data import RunData, load_run
from station.report.html import METHODS, MODELS, mass_std
from station.report.quantities import fmt_unc, fmt_value, measured_sensitivity, range_text, structure_sentence
from station.report.statement import uncertainty_statement
from station.report.tables import MEANING

RELATES_ONLY = ("The results relate only to the item calibrated, as received, under the conditions stated. "
                "This certificate shall not be reproduced except in full without the laboratory's written "
                "approval.")
DETERMINED_TEXT = {"natural_frequency_hz": "loaded natural frequency sqrt(k_f/M)/(2π)",
                   "series_stiffness": "series stiffness of transducer and coupling",
                   "S_times_M": "sensitivity times moving mass S·M", "damping_ratio": "damping ratio"}


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
            meaning: str) -> dict[str, Any]:
    if value is None or budget_entry is None or budget_entry.get("combined") is None:
        return {"name": name, "meaning": meaning, "value": value, "text": "not determined", "unit": unit,
                "u": None, "k": None, "p": None, "U": None, "nu_eff": None, "u_text": "", "U_text": "", "k_text": "",
                "determined": False}
    c = coverage(budget_entry)
    return {"name": name, "meaning": meaning, "value": value, "u": c.u, "k": c.k, "p": c.p, "U": c.U,
            "determined": False,
            "nu_eff": None if math.isinf(c.nu_eff) else c.nu_eff, "unit": unit,
            "text": fmt_value(value, c.u), "u_text": fmt_unc(c.u), "U_text": fmt_unc(c.U), "k_text": f"{c.k:.3g}"}


def register_standards(standards: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The lab register's records of the run's reference standards (``station.lab.register.Standard``
    as the run stored them) in the certificate's form."""
    return [{"name": s.get("description") or f"{s.get('kind', 'standard')} {s.get('id', '')}",
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
    rec, ident = d.rec, d.ident
    cfg = rec.config if isinstance(rec.config, dict) else {}
    results = []
    for name, p in ident.parameters.items():
        if p.identifiable and p.value is not None:
            results.append(_result(name, p.value, ident.budget.get(name), p.unit, MEANING.get(name, name)))
    for name, q in ident.determined.items():
        if "range" in q or q.get("value") is None or q.get("combined") is None:
            continue
        entry = {"contributions": {k: v for k, v in q.items() if k not in ("value", "unit", "combined", "note")
                                   and (v is None or isinstance(v, int | float))},
                 "combined": q["combined"], "dof": (ident.budget.get("k_f") or {}).get("dof")}
        results.append({**_result(name, float(q["value"]), entry, str(q.get("unit", "")),
                                  DETERMINED_TEXT.get(name, name)), "determined": True})
    r = d.response
    u_m = mass_std(ident.assumptions)
    mag, u_mag, ph, u_ph = measured_sensitivity(r.H, r.cov, d.mass_kg, u_m)
    k_points = 2.0  # each point rests on thousands of samples: nu_eff infinite, k = 2 kept (about 95.4 %)
    response = [{"f_hz": float(f), "magnitude": float(mag[i]), "U_magnitude": float(k_points * u_mag[i]),
                 "phase_deg": math.degrees(float(ph[i])), "U_phase_deg": math.degrees(float(k_points * u_ph[i])),
                 "text": fmt_value(float(mag[i]), float(u_mag[i])), "U_text": fmt_unc(float(k_points * u_mag[i])),
                 "phase_text": fmt_value(math.degrees(float(ph[i])), math.degrees(float(u_ph[i]))),
                 "U_phase_text": fmt_unc(math.degrees(float(k_points * u_ph[i])))}
                for i, f in enumerate(r.f_hz)]
    masses = []
    for key, label in (("end_mass_kg", "end mass m_e"), ("load_mass_kg", "load mass m_l")):
        a = ident.assumptions.get(key) or {}
        masses.append({"name": label, "value": a.get("value"), "std": a.get("std"), "source": a.get("source", "")})
    st = ident.assumptions.get("structure")
    budget_sources = list(next(iter(ident.budget.values()))["contributions"]) if ident.budget else []
    budget = [{"name": n, "unit": b.get("unit", ""),
               "cells": [fmt_unc(b["contributions"].get(s)) if b["contributions"].get(s) is not None else "conditional"
                         for s in budget_sources], "combined": fmt_unc(b.get("combined"))}
              for n, b in ident.budget.items()]
    tr_cfg = cfg.get("transducer")
    tr: dict[str, Any] = tr_cfg if isinstance(tr_cfg, dict) else {}
    reg = register or {}
    reg_tr = reg.get("transducer") if isinstance(reg.get("transducer"), dict) else {}
    assert isinstance(reg_tr, dict)
    standards = register_standards(reg["standards"]) if reg.get("standards") else [
        s.model_dump() for s in cc.standards]
    return {
        "approval": asdict(approval),
        "laboratory": cc.laboratory.model_dump(), "customer": None if cc.customer is None else cc.customer.model_dump(),
        "place": cc.place,
        "item": {"transducer_id": rec.transducer_id, "capacity_N": rec.capacity_N,
                 "nominal_sensitivity_V_per_N": tr.get("sensitivity_V_per_N"),
                 "signal_sensitivity_V_per_N": rec.sensitivity_V_per_N,
                 **{k: str(reg_tr.get(k) or "") for k in ("type", "serial", "owner")}},
        "run": {"run_id": rec.run_id, "recording": Path(path).name, "start_time": rec.start_time,
                "end_time": rec.end_time, "exit_status": rec.exit_status, "source": rec.source,
                "software_version": rec.software_version,
                "steps": [{"f_hz": s.crank_frequency_hz, "radius_mm": 1e3 * s.crank_radius_m} for s in rec.steps]},
        "method": {"name": "dynamic calibration by stepped sine excitation on a crank (sine-mechanism) rig",
                   "estimator": ident.method, "estimator_text": METHODS.get(ident.method, ""),
                   "model": ident.model, "model_text": MODELS.get(ident.model, ""), "result": d.ident_source},
        "environment": _environment(d),
        "standards": standards, "standards_source": "register" if reg.get("standards") else "configuration",
        "results": results, "response": response, "response_k": k_points,
        "budget": {"sources": budget_sources, "rows": budget},
        "coverage": {n: c.to_dict() for n, c in coverages(ident.budget).items()},
        "statement": uncertainty_statement(ident.budget, ident.assumptions),
        "assumptions": {"masses": masses, "M_kg": d.mass_kg, "u_M_kg": u_m,
                        "structure": structure_sentence(st) if st else "",
                        "chain": ident.assumptions.get("measurement_chain") or {},
                        "ranges": [{"name": k, "range": range_text(v["range"]), "unit": v.get("unit", ""),
                                    "conditional_on": v.get("conditional_on", "")}
                                   for k, v in ident.determined.items() if "range" in v]},
        "checks": [{"name": c.name, "severity": c.severity, "message": c.message} for c in ident.checks
                   if c.severity != "info"],
        "relates_only": RELATES_ONLY,
    }
