"""The uncertainty statement of a result, every sentence generated from the budget it describes.

Input: the budget (``{parameter: ParameterBudget}``, ``station.ident.uncertainty``) and the result's
assumptions (the masses with their source and standard uncertainty).
A source is said to be *propagated* when its contribution is a number above zero, *contributing
nothing* when it is 0 for every parameter, and *not propagated* (the result conditional on it) when
it is None.  The masses, the chain and the coverage factor are described from those facts only, so
a budget that changes changes the sentences (tests/test_certificate_statement.py).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from station.ident.coverage import coverages
from station.ident.uncertainty import ParameterBudget
from station.report.quantities import fmt_unc

SOURCE_TEXT = {"noise": "the measurement noise propagated through the fit",
               "chain_gain": "the gain ratio and flatness of the force and displacement chains",
               "chain_phase": "the phase offset and phase errors between the channels",
               "chain_delay": "the time skew between the channels",
               "chain_resonance": "the stated displacement-sensor resonance the response was corrected for",
               "end_mass": "the end mass m_e", "load_mass": "the load mass m_l (top mass and adaption)",
               "conditioner_gain": ("the reference conditioner's gain and the bridge excitation, from its "
                                    "certificate (S of the transducer alone)"),
               "radius": "the crank radius (the frame motion is the measured displacement)",
               "unidentified_dynamics": ("the stiffness and damping one frequency leaves undetermined, as uncertain "
                                         "as the estimator has them (RLS)")}
MASSES = (("end_mass", "end_mass_kg", "end mass m_e"), ("load_mass", "load_mass_kg", "load mass m_l"))


def _largest(budget: Mapping[str, ParameterBudget]) -> dict[str, tuple[str, float]]:
    """Per parameter: the source with the largest contribution and its share of u_c^2."""
    out = {}
    for n, b in budget.items():
        c = {s: float(u) for s, u in b.stds.items() if u is not None}
        uc = b.combined if math.isfinite(b.combined) else 0.0
        if c and uc > 0:
            s = max(c, key=lambda k: c[k])
            out[n] = (s, c[s] ** 2 / uc**2)
    return out


def source_status(budget: Mapping[str, ParameterBudget]) -> dict[str, str]:
    """'propagated' | 'nothing' | 'conditional' per source (over all parameters)."""
    status: dict[str, str] = {}
    for b in budget.values():
        for s, u in b.stds.items():
            now = "conditional" if u is None else "propagated" if float(u) > 0 else "nothing"
            prev = status.get(s)
            status[s] = now if prev is None or now == "propagated" or prev == "nothing" else prev
    return status


def _mass_sentence(source: str, key: str, label: str, status: str | None, assumptions: Mapping[str, Any],
                   budget: Mapping[str, ParameterBudget]) -> str:
    a = assumptions.get(key) if isinstance(assumptions.get(key), Mapping) else {}
    assert isinstance(a, Mapping)
    val = a.get("value")
    where = f" ({a.get('source')})" if a.get("source") else ""
    value = f" = {val:g} kg{where}" if isinstance(val, int | float) else where
    if status == "conditional":
        return (f"The {label}{value} is assumed, not propagated: the results that depend on it are conditional "
                "on its value and carry no uncertainty for it.")
    if status == "propagated":
        per = ", ".join(f"{fmt_unc(b.stds[source])} {b.unit} in u({n})"
                        for n, b in budget.items() if b.stds.get(source))
        std = a.get("std")
        return (f"The {label}{value} is an uncertain input"
                + (f" with standard uncertainty {fmt_unc(std)} kg" if isinstance(std, int | float) else "")
                + f"; the budget propagates it: {per}.")
    if status == "nothing":
        return f"The {label}{value} enters the budget with no effect on the results (contribution 0)."
    if a.get("source") == "campaign":
        return (f"The {label} is determined by the data jointly with the other parameters (a campaign of several "
                "top masses): its uncertainty is in the parameters' covariance, not a source of this budget.")
    return f"The {label} is not a source of this budget."


def uncertainty_statement(budget: Mapping[str, ParameterBudget], assumptions: Mapping[str, Any] | None = None,
                          p: float = 0.95, *, k2: bool = False) -> list[str]:
    """The sentences of the uncertainty statement (module docstring); [] for an empty budget.
    k2: the certificate's convention (``station.ident.coverage.coverage``: k = 2, about 95.45 %)."""
    if not budget:
        return ["No uncertainty budget is stored with this result: no uncertainty is stated."]
    assumptions = assumptions or {}
    status = source_status(budget)
    cov = coverages(budget, p, k2=k2)
    out = []
    ks = "; ".join(f"{n}: k = {c.k:.3g}, " + ("ν_eff infinite" if math.isinf(c.nu_eff) else f"ν_eff = {c.nu_eff:.3g}")
                   for n, c in cov.items())
    if k2:
        other = {n: c for n, c in cov.items() if c.k != 2.0}
        out.append("Standard uncertainties u are stated with k = 1. The expanded uncertainties U = k u are stated "
                   "with the coverage factor k = 2, which for a normal distribution corresponds to a coverage "
                   "probability of approximately 95 % (95.45 %)"
                   + ("" if not other else "; where the effective degrees of freedom ν_eff (Welch–Satterthwaite) are "
                      "too few for k = 2, k is the t-distribution's quantile for 95.45 % at ν_eff: "
                      + "; ".join(f"{n}: k = {c.k:.3g}, ν_eff = {c.nu_eff:.3g}" for n, c in other.items()))
                   + ".")
    else:
        out.append(f"Standard uncertainties u are stated with k = 1; expanded uncertainties U = k u for a coverage "
                   f"probability of {100 * p:.0f} %, k the t-distribution's quantile at the effective degrees of "
                   f"freedom ν_eff (Welch–Satterthwaite) of each result ({ks}).")
    prop = [s for s, v in status.items() if v == "propagated"]
    if prop:
        out.append("The budget propagates " + "; ".join(SOURCE_TEXT.get(s, s) for s in prop) + ".")
    largest = _largest(budget)
    if largest:
        out.append("Largest contribution: " + "; ".join(f"to u({n}) {SOURCE_TEXT.get(s, s)} ({100 * share:.0f} % of u²)"
                                                        for n, (s, share) in largest.items()) + ".")
    for source, key, label in MASSES:
        out.append(_mass_sentence(source, key, label, status.get(source), assumptions, budget))
    nothing = [s for s, v in status.items() if v == "nothing" and s not in dict((m[0], 1) for m in MASSES)]
    if nothing:
        out.append("Contributing nothing: " + "; ".join(SOURCE_TEXT.get(s, s) for s in nothing) + ".")
    cond = [s for s, v in status.items() if v == "conditional" and s not in dict((m[0], 1) for m in MASSES)]
    if cond:
        out.append("Not propagated (the results are conditional on them): "
                   + "; ".join(SOURCE_TEXT.get(s, s) for s in cond) + ".")
    finite: dict[str, float] = {}
    for b in budget.values():
        finite.update(b.dof)
    if finite:
        out.append("Finite degrees of freedom: " + "; ".join(f"{SOURCE_TEXT.get(s, s)} ν = {n:g}"
                                                              for s, n in sorted(finite.items()))
                   + " (the noise scaled by χ²/dof from the fit's residuals); all other sources are taken with "
                   "infinite degrees of freedom.")
    else:
        out.append("Every source is taken with infinite degrees of freedom (the noise from the sine fits of "
                   "thousands of samples per step, the others Type B).")
    return out
