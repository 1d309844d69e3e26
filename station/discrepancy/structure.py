"""The structure the transducer parameters rest on, stated with them (like the end mass).

Below the coupling's own signature (paper Eq. 8 against Eq. 9) a stepped-sine plan determines the
*series* stiffness of transducer and coupling, k_s = (1/k_f + 1/k_c)^-1, not k_f alone.  Unless the
final model names a coupling, ``parameters_after`` is therefore k_f of the transducer alone *under
the assumption of a stiff coupling* (Eq. 9), and the report says so: the series stiffness the data
determine (in the stiff model, its k_f), the coupling model refitted on top of the final one (its k_f
and k_c, and how much it improves the fit), and the range of k_f alone that follows (two standard
uncertainties of that model, never below k_s), or that these data do not determine k_f alone.  With
a coupling named, the model is Eq. 8 and k_s follows from k_f, k_c and their covariance.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np

from station.discrepancy.catalogue import KC_TOP
from station.discrepancy.data import RigData
from station.discrepancy.estimates import EstimateJson
from station.discrepancy.fit import ModelFit
from station.discrepancy.search import Candidate, fit_candidate
from station.ident.result import Estimate

COUPLING = "coupling_compliance"
UNDETERMINED = 0.5  # relative standard uncertainty of k_f above which k_f alone is called not determined


class StructureJson(TypedDict):
    """``Structure.to_json``: stiffnesses in N/m as estimates (None when not fitted), the scaled Delta chi^2,
    k_f alone's (low, high) range in N/m or None, the sentence."""

    model: str
    series_stiffness: EstimateJson
    k_f_coupling_free: EstimateJson | None
    k_c: EstimateJson | None
    delta_chi2: float | None
    k_f_alone_range: list[float] | None
    message: str


@dataclass(frozen=True)
class Structure:
    """model: the structure ``parameters_after`` rests on; series_stiffness: what the data determine
    (N/m); k_f_coupling_free / k_c: the final model with a coupling free (None if not fitted); delta_chi2:
    its chi^2 improvement (scaled by the Birge ratio); k_f_alone_range: (low, high) N/m or None when not
    determined; message: one sentence."""

    model: str
    series_stiffness: Estimate
    k_f_coupling_free: Estimate | None
    k_c: Estimate | None
    delta_chi2: float | None
    k_f_alone_range: tuple[float, float] | None
    message: str
    coupled: ModelFit | None = field(default=None, compare=False, repr=False)  # the model with a coupling free

    def to_json(self) -> StructureJson:
        return {"model": self.model, "series_stiffness": self.series_stiffness.to_dict(),
                "k_f_coupling_free": None if self.k_f_coupling_free is None else self.k_f_coupling_free.to_dict(),
                "k_c": None if self.k_c is None else self.k_c.to_dict(),
                "delta_chi2": None if self.delta_chi2 is None else float(self.delta_chi2),
                "k_f_alone_range": None if self.k_f_alone_range is None else list(self.k_f_alone_range),
                "message": self.message}


def _series(fit: ModelFit) -> Estimate:
    """k_s = k_f k_c / (k_f + k_c) with its standard uncertainty from the covariance (delta method)."""
    names = [q.name for q in fit.params]
    kf, kc = fit.values["k_f"], fit.values["k_c"]
    ks = kf * kc / (kf + kc)
    g = np.zeros(len(names))
    g[names.index("k_f")] = (kc / (kf + kc)) ** 2
    g[names.index("k_c")] = (kf / (kf + kc)) ** 2
    return Estimate(ks, float(math.sqrt(max(float(g @ fit.cov @ g), 0.0))), "N/m")


def state_structure(data: RigData, final: ModelFit, last: Sequence[tuple[Candidate, ModelFit]]) -> Structure | None:
    """The structure of the final model and what a coupling would change (module docstring); None when
    a coupling cannot be tested (no end mass, fewer than 3 steps)."""
    if COUPLING in final.effects:
        ks = _series(final)
        return Structure("coupled: transducer and a compliant coupling in series (paper Eq. 8)", ks, None, None,
                         None, None, f"coupling named: the series stiffness of transducer and coupling is "
                         f"{ks.value:.6g} N/m (series_stiffness); k_f and k_c are given separately")
    stiff = Estimate(final.values["k_f"], final.std["k_f"], "N/m")
    found = next(((c, f) for c, f in last if c.name == COUPLING), None)
    cpl = found[1] if found is not None else fit_candidate(data, final, COUPLING)
    if cpl is None:
        return None
    d = found[0].delta_chi2 if found is not None else max(final.chi2 - cpl.chi2, 0.0) / max(final.birge, 1.0)
    kf = Estimate(cpl.values["k_f"], cpl.std["k_f"], "N/m")
    kc = Estimate(cpl.values["k_c"], cpl.std["k_c"], "N/m")
    model = "stiff coupling (paper Eq. 9): k_f is of the transducer alone only if the coupling is stiff"
    k, u_k = float(cpl.values["k_f"]), float(cpl.std["k_f"])
    s_k, u_s = float(final.values["k_f"]), float(final.std["k_f"])
    u_c = float(cpl.std["k_c"])
    # k_c undetermined: a large u(k_c), or the fit resting beyond the stiffest coupling of its start grid
    # (the rigid limit, where k_c's linearised u is that of a model that no longer depends on it)
    k_c = float(cpl.values["k_c"])
    k_c_free = not (math.isfinite(u_c) and u_c < UNDETERMINED * abs(k_c)) or k_c >= KC_TOP * k
    if not (math.isfinite(u_k) and u_k < UNDETERMINED * abs(k)) or k_c_free:
        # with k_c undetermined (the coupled fit resting in the rigid limit) k_f's linearised u is
        # conditional on that k_c: any stiffer transducer with a softer coupling fits as well
        why = (f"k_f rests on a stiff coupling: these data determine the series stiffness of transducer "
               f"and coupling, {s_k:.6g} N/m (series_stiffness); with a coupling free (Delta chi2 "
               f"{d:.3g}) " + (f"k_c is not determined ({kc.value:.3g} ± {kc.std:.2g} N/m), so neither is "
                               "k_f alone" if k_c_free else f"k_f alone is {k:.4g} ± {u_k:.2g} N/m") +
               ": not determined by this plan (steps near the resonances would separate them: see proposal)")
        return Structure(model, stiff, kf, kc, d, None, why, coupled=cpl)
    lo, hi = max(k - 2 * u_k, s_k - 2 * u_s), k + 2 * u_k
    return Structure(model, stiff, kf, kc, d, (lo, hi),
                     f"k_f rests on a stiff coupling: these data determine the series stiffness of transducer and "
                     f"coupling, {s_k:.6g} N/m (series_stiffness); with a coupling free (Delta chi2 {d:.3g}, "
                     f"k_c = {kc.value:.3g} ± {kc.std:.2g} N/m) k_f alone is {k:.6g} ± {u_k:.2g} N/m, "
                     f"range {lo:.4g}-{hi:.4g} N/m")
