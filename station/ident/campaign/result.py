"""Frozen result types of a multi-mass campaign (``campaign.identify.identify_campaign``) and their JSON form.

JSON (``station identify REC1 REC2 ... --json``, ``POST /campaigns``): ``status`` ('separated',
'conditional' or 'refused'), ``parameters`` {S, m_e, k_f, b_f: value, std, unit, identifiable[,
flag, reason]}, ``covariance`` {names, units, matrix}, ``recordings`` (per recording: its load mass
as weighed and as fitted, the steps used, its chi^2 share, S and k_f of its own fit), ``fit``
{chi2, dof, chi2_per_dof, inflated}, ``checks``, ``budget`` (each source's covariance over the
budgeted parameters is in ``CampaignResult.budget``, not in the JSON, whose ``covariance`` is their sum),
``assumptions``, ``determined``,
``notes`` (shared conventions of the identification result).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from station.ident.assumptions import CampaignAssumptions
from station.ident.result import Check, Estimate, JsonValue
from station.ident.uncertainty import Covariance, DeterminedQuantity, UncertaintyBudget

FloatArray = NDArray[np.float64]


def _f(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


@dataclass(frozen=True)
class CampaignRecording:
    """One recording of the campaign: path, run id, load mass m_l as weighed (value, std; kg) and as
    fitted (kg), the steps used and their frequency range (Hz), chi^2 of its H(f) against the joint
    model over its 2 n_steps real numbers, and S (V/N), k_f (N/m) with standard uncertainties from
    its own Eq. 9 fit with m_e held at the campaign's (for the consistency check)."""

    path: str
    run_id: str
    load_mass_kg: float
    load_mass_std_kg: float
    load_mass_fitted_kg: float
    load_mass_fitted_std_kg: float
    steps_used: tuple[int, ...]
    f_range_hz: tuple[float, float]
    chi2: float
    S: tuple[float, float]
    k_f: tuple[float, float]

    def to_dict(self) -> dict[str, JsonValue]:
        return {"path": self.path, "run_id": self.run_id,
                "load_mass_kg": {"value": self.load_mass_kg, "std": self.load_mass_std_kg},
                "load_mass_fitted_kg": {"value": _f(self.load_mass_fitted_kg),
                                        "std": _f(self.load_mass_fitted_std_kg)},
                "steps_used": list(self.steps_used), "f_range_hz": list(self.f_range_hz),
                "chi2": _f(self.chi2), "n_real": 2 * len(self.steps_used),
                "own_fit": {"S": {"value": _f(self.S[0]), "std": _f(self.S[1]), "unit": "V/N"},
                            "k_f": {"value": _f(self.k_f[0]), "std": _f(self.k_f[1]), "unit": "N/m"}}}


@dataclass(frozen=True)
class CampaignResult:
    """Joint identification of one transducer from recordings with different top masses.

    status: 'separated' (S and m_e determined by the data), 'conditional' (the masses cannot separate
    them: S, k_f, b_f conditional on the stated end mass, m_e refused), 'refused' (not separable and
    no end mass stated: only ``determined`` is given); parameters: S, m_e, k_f, b_f; covariance
    (4, 4) in their units (zeros for a refused parameter); budget per parameter (GUM: contributions and the
    combined standard uncertainty = sqrt of cov's diagonal)."""

    status: str
    transducer_id: str
    parameters: dict[str, Estimate]
    covariance: Covariance
    recordings: tuple[CampaignRecording, ...]
    chi2: float
    dof: int
    inflated: bool
    checks: tuple[Check, ...]
    budget: UncertaintyBudget
    assumptions: CampaignAssumptions
    determined: dict[str, tuple[DeterminedQuantity, ...]]
    notes: tuple[str, ...] = ()

    @property
    def chi2_per_dof(self) -> float:
        return self.chi2 / self.dof if self.dof else float("nan")

    def parameter(self, name: str) -> Estimate:
        return self.parameters[name]

    def to_dict(self) -> dict[str, JsonValue]:
        return {"kind": "campaign", "method": "fd", "model": "sdof", "status": self.status,
                "transducer_id": self.transducer_id,
                "parameters": {n: p.to_dict() for n, p in self.parameters.items()},
                "covariance": self.covariance.to_dict(),
                "recordings": [r.to_dict() for r in self.recordings],
                "fit": {"chi2": _f(self.chi2), "dof": self.dof, "chi2_per_dof": _f(self.chi2_per_dof),
                        "inflated": self.inflated},
                "checks": [c.to_dict() for c in self.checks], "budget": self.budget.to_dict(),
                "assumptions": self.assumptions.to_dict(),
                "determined": {n: [q.to_dict() for q in qs] for n, qs in self.determined.items()},
                "notes": list(self.notes)}
