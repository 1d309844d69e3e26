"""The result a certificate states: one run's stored identification, or the multi-mass campaign the
run belongs to when one is stored beside it and the data separated S from the end mass.

A campaign (``station identify A B C`` / ``POST /campaigns``, stored as ``results/campaign`` beside
every recording of it) determines m_e from the data; its certificate carries S, m_e, k_f, b_f with
the joint covariance, the masses of every run, and this run's derived quantities and S_dyn(f) with
M = m_e (determined) + m_l (this run's).  A campaign that could not separate them ('conditional',
'refused') is not used: the run's own result, with its assumed end mass stated, is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from station.ident.result import Check, Estimate, estimates_from_dict
from station.ident.uncertainty import Covariance, determined_to_dict
from station.report.data import RunData

CAMPAIGN = "campaign"  # station.ident.campaign.identify.RESULT_NAME


@dataclass(frozen=True)
class Certified:
    """kind 'run' | 'campaign'; the values the certificate states and where they come from; mass_kg
    and mass_std_kg: M = m_e + m_l of this run and u(M); runs: the campaign's recordings (run id,
    top + adaption mass) or []."""

    kind: str
    method: str
    model: str
    source: str
    parameters: dict[str, Estimate]
    budget: dict[str, Any]
    determined: dict[str, Any]
    assumptions: dict[str, Any]
    checks: tuple[Check, ...]
    covariance: Covariance | None
    mass_kg: float
    mass_std_kg: float
    runs: list[dict[str, Any]] = field(default_factory=list)


def _campaign(d: RunData) -> Certified | None:
    stored = d.results.get(CAMPAIGN)
    if stored is None:
        return None
    c = stored.payload
    run_id = d.rec.run_id
    runs = c.get("recordings") or []
    if (c.get("status") != "separated" or c.get("transducer_id") != d.rec.transducer_id
            or run_id not in [r.get("run_id") for r in runs]):
        return None
    params = estimates_from_dict(c.get("parameters"))
    a = dict(c.get("assumptions") or {})
    loads = a.get("load_mass_kg")
    mine = next((m for m in loads if m.get("run_id") == run_id), None) if isinstance(loads, list) else None
    if mine is None or not params.get("m_e") or params["m_e"].value is None:
        return None
    a["load_mass_kg"] = {"value": mine.get("value"), "std": mine.get("std"), "source": "weighed (this run)"}
    determined = {}
    for name, entries in (c.get("determined") or {}).items():
        entry = entries if isinstance(entries, dict) else next(
            (e for e in entries if isinstance(e, dict) and e.get("run_id") == run_id), None)
        if entry is not None:
            determined[name] = {k: v for k, v in entry.items() if k != "run_id"}
    m_e, u_e = params["m_e"].value, params["m_e"].std or 0.0
    m_l, u_l = float(mine.get("value") or 0.0), float(mine.get("std") or 0.0)
    cov = c.get("covariance")
    return Certified(
        CAMPAIGN, str(c.get("method", "fd")), str(c.get("model", "sdof")),
        f"results/{CAMPAIGN} (a joint fit of {len(runs)} runs with different top masses, written {stored.written})",
        params, dict(c.get("budget") or {}), determined, a,
        tuple(Check.from_dict(x) for x in c.get("checks") or []),
        Covariance(tuple(cov["names"]), tuple(cov["units"]), tuple(tuple(map(float, r)) for r in cov["matrix"]))
        if isinstance(cov, dict) else None,
        float(m_e) + m_l, math.hypot(u_e, u_l),
        [{"run_id": r.get("run_id"), "load_mass_kg": (r.get("load_mass_kg") or {}).get("value"),
          "f_range_hz": r.get("f_range_hz")} for r in runs])


def certified_of(d: RunData) -> Certified:
    """The campaign's result when a separated one covers this run (module docstring), else the run's."""
    camp = _campaign(d)
    if camp is not None:
        return camp
    i = d.ident
    return Certified("run", i.method, i.model, d.ident_source, dict(i.parameters), i.budget.to_dict(),
                     determined_to_dict(i.determined), i.assumptions.to_dict(), tuple(i.checks), i.covariance,
                     d.mass_kg, i.assumptions.mass_std_kg)
