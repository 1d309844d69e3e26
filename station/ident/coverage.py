"""Expanded uncertainty of a budget entry: effective degrees of freedom and coverage factor.

GUM G.4: nu_eff = u_c^4 / sum_i (u_i^4 / nu_i) over the sources (Welch-Satterthwaite), the Type B
sources and a noise term resting on many samples with nu_i infinite; k is the t-distribution's
(1 + p)/2 quantile at nu_eff (the normal one for infinite nu_eff), U = k u_c.  A budget entry is a
``station.ident.uncertainty.ParameterBudget`` (its stored form read back by ``ParameterBudget.from_dict``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from scipy.special import ndtri, stdtrit  # the quantiles scipy.stats computes, without its import (0.6 s)

from station.ident.uncertainty import ParameterBudget
from station.jsonvalue import JsonValue

COVERAGE_PROBABILITY = 0.95
K2_PROBABILITY = 0.9545  # the normal distribution's coverage probability of k = 2 (GUM G.1.3)


@dataclass(frozen=True)
class Coverage:
    """u: combined standard uncertainty; nu_eff: effective degrees of freedom (inf when every source
    is infinite); k: coverage factor for probability p; U = k u (all in the entry's unit)."""

    u: float
    nu_eff: float
    k: float
    p: float

    @property
    def U(self) -> float:
        return self.k * self.u

    def to_dict(self) -> dict[str, JsonValue]:
        return {"u": self.u, "nu_eff": None if math.isinf(self.nu_eff) else self.nu_eff, "k": self.k, "p": self.p,
                "U": self.U}


def coverage_factor(nu_eff: float, p: float = COVERAGE_PROBABILITY) -> float:
    """k for coverage probability p at nu_eff degrees of freedom (t-distribution; normal when infinite)."""
    q = (1 + p) / 2
    return float(ndtri(q) if math.isinf(nu_eff) else stdtrit(nu_eff, q))  # norm.ppf(q), t.ppf(q, nu_eff)


def effective_dof(contributions: Mapping[str, float | None], dof: Mapping[str, float] | None) -> float:
    """Welch-Satterthwaite over the sources (None contributions are not propagated and ignored)."""
    us = {s: float(u) for s, u in contributions.items() if u is not None}
    uc2 = sum(u * u for u in us.values())
    finite = {s: float(n) for s, n in (dof or {}).items() if s in us and n is not None and math.isfinite(n)}
    denom = sum(us[s] ** 4 / max(n, 1e-300) for s, n in finite.items())
    if denom <= 0 or uc2 <= 0:
        return math.inf
    return uc2 * uc2 / denom


def coverage(entry: ParameterBudget, p: float = COVERAGE_PROBABILITY, *, k2: bool = False) -> Coverage:
    """The Coverage of one budget entry (module docstring).  k2: the calibration certificate's
    convention (EA-4/02): k = 2 for a coverage probability of about 95.45 %, unless nu_eff is so
    small that the t-quantile exceeds 2 by more than its rounding (then that k, nu_eff stated)."""
    nu = effective_dof(entry.stds, entry.dof)
    if k2:
        k = coverage_factor(nu, K2_PROBABILITY)
        return Coverage(entry.combined, nu, 2.0 if k < 2.005 else k, K2_PROBABILITY)
    return Coverage(entry.combined, nu, coverage_factor(nu, p), p)


def coverages(budget: Mapping[str, ParameterBudget], p: float = COVERAGE_PROBABILITY, *,
              k2: bool = False) -> dict[str, Coverage]:
    """Coverage per parameter of a budget (k2: ``coverage``'s certificate convention); parameters
    without a finite combined uncertainty are left out."""
    return {n: coverage(b, p, k2=k2) for n, b in budget.items() if math.isfinite(b.combined)}
