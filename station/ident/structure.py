"""The model's structure as a stated assumption: the coupling of the load mass (stiff, Eq. 9, or
finite, Eq. 8) and the displacement chain's frequency response (flat, or a sensor resonance).

**Coupling.**  Below the coupled mode, a coupling k_c in series with the transducer's k_f shows as
one spring of the *series* stiffness 1/k_s = 1/k_f + 1/k_c (exactly in the static limit; the
remaining signature is a frequency-dependent stiffness and damping of relative size ~ (w b_f/k_f)^2
k_f/(k_f + k_c), which the stiff-coupling fit partly absorbs).  What the data determine under Eq. 9
is therefore k_s; the transducer's k_f alone rests on the assumption k_c -> inf.  How far that
assumption reaches is a property of the plan: ``coupling_bound`` asks, for couplings k_c = r k_s
over a grid of r, how much misfit Eq. 9 would show if the truth were Eq. 8 with that k_c (b_c = 0)
and the fitted series behaviour: the weighted chi^2 of the best Eq. 9 fit to that Eq. 8 response
(the non-centrality lambda), against the measured covariance of H (times the Birge factor when Eq. 9
already misfits).  A coupling is *detectable* when the misfit check
(chi^2/dof > 1 + 3 sqrt(2/dof), ``response.frf.fit_frf``) would fire with probability >= ``DETECTION_POWER``
(non-central chi^2).  The undetectable couplings give the range of k_f (and b_f) alone; the
softest of them is the lower bound on k_c this plan supports.

**Displacement chain.**  A displacement sensor with its own resonance f_r (damping ratio p) reads
x_m = H_s x_b, H_s = w_r^2 / (w_r^2 - w^2 + 2 j p w_r w) (``drivers.rig.params.DisplacementResonance``),
so the measured H(f) is H / H_s.  When the chain states a resonance, ``chain_corrected`` multiplies
H(f) by H_s; ``fd.budget.resonance_vectors`` give the budget's ``chain_resonance`` source (u(f_r), u(p)).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.special import chndtr  # the non-central chi^2 without scipy.stats (0.6 s of CPU per worker start)

from drivers.rig.params import DisplacementResonance
from station.config import MeasurementChain
from station.ident.assumptions import CouplingStatement, StructureStatement
from station.ident.inputs import IdentInputs
from station.ident.models import CoupledModel, SdofModel, make_model
from station.ident.response import frf as frfmod
from station.ident.result import Check, Estimate, JsonValue
from station.ident.uncertainty import DeterminedQuantity
from station.vocabulary import Flag, Severity

if TYPE_CHECKING:
    from station.ident.fd.budget import Budget

FloatArray = NDArray[np.float64]
DETECTION_POWER = 0.95
# couplings tried: k_c = (1 + x) k_s, x within 1e-2 ... 1e6 (x -> 0: all the compliance in the coupling)
_X_MIN, _X_MAX = 1e-2, 1e6
# an adapter or a screwed-on top mass can be as little as tens of times stiffer than the transducer:
# a plan that cannot exclude couplings below this many k_s leaves k_f alone open by more than ~1 %
ADAPTER_COUPLING_RATIO = 100.0
# and none is ten times softer than the transducer it carries: a fit that says so is not physical
MIN_PLAUSIBLE_COUPLING_RATIO = 0.1
STIFF = "stiff coupling (Eq. 9: k_c -> inf, b_c -> 0)"
COUPLED = "coupled (Eq. 8: finite k_c, b_c)"


# ---- displacement chain -----------------------------------------------------------------------

def chain_corrected(frf: frfmod.FrequencyResponse, chain: MeasurementChain) -> frfmod.FrequencyResponse:
    """H(f) corrected for the stated displacement-sensor resonance (H H_s, covariance rotated and
    scaled alike); unchanged for a flat chain."""
    res = chain.displacement_resonance
    if res is None:
        return frf
    hs = np.asarray(res.response(frf.f_hz), dtype=np.complex128)
    R = np.array([[[z.real, -z.imag], [z.imag, z.real]] for z in hs])
    cov = np.einsum("fij,fjk,flk->fil", R, frf.cov, R)
    return frfmod.FrequencyResponse(frf.f_hz, frf.H * hs, cov, frf.force_rms_residual_V, frf.force_offset_V)


# ---- coupling -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class CouplingBound:
    """What this plan can tell about the coupling, under Eq. 9's fitted series behaviour.

    k_c_min: the softest coupling (N/m) the plan would not flag (None: every coupling down to
    1.01 k_s would be flagged, i.e. the plan rules couplings out; inf never: see k_f_high);
    k_f_high, b_f_high: the largest k_f (N/m) and b_f (N s/m) alone among the undetectable couplings
    (None: unbounded, the plan cannot tell k_f alone); lambda_needed: the non-centrality at which the
    misfit check fires with DETECTION_POWER; threshold_chi2: that check's chi^2."""

    k_s: float
    b_s: float
    k_c_min: float | None
    k_f_high: float | None
    b_f_high: float | None
    lambda_needed: float
    threshold_chi2: float

    def to_dict(self) -> dict[str, JsonValue]:
        return {"k_c_lower_bound_N_per_m": None if self.k_c_min is None else float(self.k_c_min),
                "k_c_lower_bound_over_k_s": None if self.k_c_min is None else self.k_c_min / self.k_s,
                "k_f_alone_range_N_per_m": [self.k_s, self.k_f_high],
                "b_f_alone_range_N_s_per_m": [self.b_s, self.b_f_high],
                "detection_power": DETECTION_POWER, "lambda_needed": self.lambda_needed,
                "basis": "couplings softer than the lower bound would make Eq. 9 misfit (chi^2/dof above "
                         f"{self.threshold_chi2:.4g} / dof) with probability >= {DETECTION_POWER:g} at this "
                         "plan's frequencies against the stated noise and chain floor"}


@functools.lru_cache(maxsize=256)
def noncentrality_needed(dof: int, threshold: float) -> float:
    """Non-centrality at which P(chi^2_{dof, lambda} > threshold) = DETECTION_POWER (bisection; 60
    evaluations of the non-central chi^2 tail, once per degrees of freedom and threshold)."""
    lo, hi = 0.0, 10.0 * threshold + 100.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if 1.0 - float(chndtr(threshold, dof, mid)) < DETECTION_POWER:  # ncx2.sf
            lo = mid
        else:
            hi = mid
    return hi


def coupling_bound(frf: frfmod.FrequencyResponse, sdof: SdofModel, theta: FloatArray,
                   birge: float = 1.0) -> CouplingBound | None:
    """The couplings this plan cannot tell from a stiff one (module docstring); None when Eq. 9's
    fit has no degrees of freedom left (fewer than 2 frequencies).

    lambda(k_c) falls monotonically as k_c grows, as (k_s/k_c)^2 once k_c >> k_s (checked over
    k_c = 1.01 ... 1e6 k_s on the shipped plans), so a few fits along that power law, kept inside a
    bracket, find where it crosses the detection level; the bound is taken on the undetectable side."""
    n_f = int(np.unique(np.round(frf.f_hz, 6)).size)
    dof = 2 * frf.f_hz.size - 3
    S, k_s, b_s = (float(v) for v in theta)
    if n_f < 2 or dof < 1 or not (k_s > 0 and b_s > 0):
        return None
    threshold = dof + 3.0 * np.sqrt(2.0 * dof)
    need = noncentrality_needed(dof, threshold)
    # Eq. 8 needs an end mass; with none given (results conditional on 0 kg) a small one stands in:
    # the low-frequency signature of a coupling does not depend on it
    cm = make_model("coupled", max(sdof.m_e, 1e-3 * sdof.M), sdof.m_l - max(0.0, 1e-3 * sdof.M - sdof.m_e))
    assert isinstance(cm, CoupledModel)
    target = frfmod.FrequencyResponse(frf.f_hz, sdof.response(theta, frf.f_hz), frf.cov * max(birge, 1.0),
                                      frf.force_rms_residual_V, frf.force_offset_V)
    free = np.array([True, True, True, False, False])

    def misfit(x: float) -> tuple[float, float, float]:
        """(lambda, k_f, b_f) of the Eq. 8 truth with k_c = (1 + x) k_s seen through Eq. 9."""
        k_c = (1.0 + x) * k_s
        k_f = 1.0 / (1.0 / k_s - 1.0 / k_c)
        th0 = np.array([S, k_f, b_s * ((k_f + k_c) / k_c) ** 2, k_c, 0.0])
        try:
            with np.errstate(all="ignore"):
                fit = frfmod.fit_frf(target, cm, th0, free=free, inflate=False)
        except (ValueError, np.linalg.LinAlgError):
            return np.inf, k_f, float(th0[2])
        ok = np.all(np.isfinite(fit.theta))
        return (fit.chi2 if ok else np.inf), float(fit.theta[1]), float(fit.theta[2])

    lo, hi = _X_MIN, _X_MAX
    at_lo = misfit(lo)
    if at_lo[0] < need:  # even a coupling as soft as the transducer itself hides: k_f alone unbounded
        return CouplingBound(k_s, b_s, float((1.0 + lo) * k_s), None, None, need, threshold)
    best = misfit(hi)
    if best[0] >= need:  # every coupling up to 1e6 k_s would show: the plan rules couplings out
        return CouplingBound(k_s, b_s, None, k_s, b_s, need, threshold)
    x = 10.0
    for _ in range(8):
        m = misfit(x)
        if m[0] >= need:
            lo = x
        else:
            hi, best = x, m
            if m[0] > need / 1.1:
                break
        step = x * np.sqrt(max(m[0], 1e-300) / need) * (1.02 if m[0] >= need else 1.0)
        x = step if lo < step < hi else float(np.sqrt(lo * hi))
    k_c_min = float((1.0 + hi) * k_s)
    return CouplingBound(k_s, b_s, k_c_min, max(best[1], k_s), max(best[2], b_s), need, threshold)


def series_stiffness(model_key: str, theta: FloatArray, cov: FloatArray) -> tuple[float, float]:
    """k_s = 1/(1/k_f + 1/k_c) (Eq. 8) or k_f (Eq. 9) and its standard uncertainty from cov (the
    combined covariance of theta)."""
    if model_key == "sdof" or theta.size < 4:
        return float(theta[1]), float(np.sqrt(max(cov[1, 1], 0.0)))
    k_f, k_c = float(theta[1]), float(theta[3])
    k_s = 1.0 / (1.0 / k_f + 1.0 / k_c)
    g = np.zeros(theta.size)
    g[1], g[3] = (k_s / k_f) ** 2, (k_s / k_c) ** 2
    return k_s, float(np.sqrt(max(float(g @ cov @ g), 0.0)))


def plausible_coupling(theta: FloatArray) -> bool:
    """An Eq. 8 parameter set a rig can have: positive stiffnesses, non-negative dampings and a
    coupling not far softer than the transducer (k_c >= MIN_PLAUSIBLE_COUPLING_RATIO k_f)."""
    _, k_f, b_f, k_c, b_c = (float(v) for v in theta)
    return bool(np.all(np.isfinite(theta)) and k_f > 0 and k_c >= MIN_PLAUSIBLE_COUPLING_RATIO * k_f
                and b_f >= 0 and b_c >= 0)


def coupling_suspected(frf: frfmod.FrequencyResponse, sdof_chi2: float, sdof_dof: int,
                       coupled_theta: FloatArray, coupled_chi2: float, coupled_dof: int) -> Check | None:
    """A finding when Eq. 9 misfits beyond the noise and a coupling explains most of the misfit."""
    if coupled_dof < 1 or sdof_dof < 1 or not np.all(np.isfinite(coupled_theta)):
        return None
    s2, c2 = sdof_chi2 / sdof_dof, coupled_chi2 / coupled_dof
    if not (c2 < 0.5 * s2 and plausible_coupling(coupled_theta)):
        return None
    k_f, k_c = float(coupled_theta[1]), float(coupled_theta[3])
    return Check("coupling_suspected", Severity.WARNING, None,
                 f"Eq. 9 (stiff coupling) misfits the measured H(f) (chi2/dof {s2:.3g}) and a finite coupling "
                 f"explains it (Eq. 8: chi2/dof {c2:.3g}, k_c about {k_c:.3g} N/m = {k_c / k_f:.2g} k_f, k_f about "
                 f"{k_f:.3g} N/m): this plan determines the series stiffness of transducer and coupling, not the "
                 "transducer's k_f alone; add steps at higher frequencies (station discrepancy proposes them)",
                 {"chi2_per_dof_stiff": s2, "chi2_per_dof_coupled": c2, "k_c_N_per_m": k_c,
                  "k_f_coupled_N_per_m": k_f})


def structure_statement(model_key: str, stiff: bool, inputs: IdentInputs, bound: CouplingBound | None = None,
                        suspected: bool = False) -> StructureStatement:
    """The ``structure`` entry of a result's assumptions: which model it rests on (stiff: the values
    are Eq. 9's, also when the coupled model was asked for and k_c is held in the stiff limit)."""
    coupled = not stiff
    coupling = None if coupled else CouplingStatement("the series stiffness 1/(1/k_f + 1/k_c)",
                                                      {} if bound is None else bound.to_dict(), suspected)
    return StructureStatement(COUPLED if coupled else STIFF, "Eq. 8" if coupled else "Eq. 9",
                              inputs.chain.displacement_statement(), coupling)


@dataclass(frozen=True)
class StructureOutcome:
    """What the stated structure does to a stiff-coupling result: the parameters (k_f, b_f flagged
    'conditional' or withheld), findings, the ``determined`` entries and the ``structure`` statement."""

    parameters: dict[str, Estimate]
    checks: tuple[Check, ...]
    determined: dict[str, DeterminedQuantity]
    statement: StructureStatement


def _conditional(p: Estimate, text: str) -> Estimate:
    return replace(p, flag=p.flag or Flag.CONDITIONAL, reason=(p.reason + "; " if p.reason else "") + text)


def state_stiff(params: dict[str, Estimate], k_range: tuple[float, float | None] | None,
                subject: str = "the data") -> dict[str, Estimate]:
    """k_f and b_f of an Eq. 9 result (the joint fit of a campaign, the model gap's) stated as
    ``apply_structure`` states them: k_f is the series stiffness of transducer and coupling; with the
    range of k_f alone (``k_range``: (k_s, high), high None when unbounded; None: the coupling is not
    tested) wider than u(k_f) or reaching outside k_f +- u(k_f), k_f and b_f are flagged 'conditional', else
    k_f only says so."""
    out = dict(params)
    kf, bf = out.get("k_f"), out.get("b_f")
    if kf is None or not kf.identifiable or kf.value is None:
        return out
    if k_range is None:
        where, soft = "the coupling is not tested", True
    elif k_range[1] is None:
        where, soft = f"{subject} cannot tell a soft coupling from a stiff one, so k_f alone is not bounded above", True
    else:
        where = (f"k_f alone lies in [{k_range[0]:.6g}, {k_range[1]:.6g}] N/m under the couplings {subject} "
                 "cannot exclude")
        # conditional when the range is wider than u(k_f), or reaches outside k_f +- u(k_f) (a coupled fit
        # that puts k_f alone away from the series stiffness the stiff model states)
        u = float(kf.std or 0.0)
        soft = (k_range[1] - k_range[0] > u or k_range[0] < kf.value - u or k_range[1] > kf.value + u)
    text = (f"conditional on a stiff coupling (Eq. 9): {subject} determine the series stiffness of transducer and "
            f"coupling; {where}")
    out["k_f"] = _conditional(kf, text) if soft else replace(kf, reason="; ".join(filter(None, (kf.reason, text))))
    if soft and bf is not None and bf.identifiable:
        out["b_f"] = _conditional(bf, "conditional on a stiff coupling (Eq. 9): a coupling's damping would be in "
                                      "it too")
    return out


def apply_structure(model_key: str, stiff: bool, params: dict[str, Estimate], theta: FloatArray,
                    budget: Budget, frf: frfmod.FrequencyResponse, sdof: SdofModel, birge: float,
                    inputs: IdentInputs, suspected: Check | None) -> StructureOutcome:
    """State the structure of an FD result and what follows from it (module docstring).

    stiff: the values are those of Eq. 9 (the sdof model, or the coupled one with k_c held in the
    stiff limit); theta: the fitted parameters (Eq. 9's three first); budget: their GUM budget."""
    out = dict(params)
    checks: list[Check] = []
    determined: dict[str, DeterminedQuantity] = {}
    kf = out["k_f"]
    if not (budget.free[1] and kf.identifiable):
        return StructureOutcome(out, (), {}, structure_statement(model_key, stiff, inputs))
    grad = np.zeros(theta.size)
    if stiff:
        k_s = float(theta[1])
        grad[1] = 1.0
    else:
        k_s, _ = series_stiffness("coupled", theta, budget.cov)
        grad[1], grad[3] = (k_s / theta[1]) ** 2, (k_s / theta[3]) ** 2
    determined["series_stiffness"] = DeterminedQuantity(
        k_s, "N/m", budget.budget_of(grad, "N/m"),
        note="1/k_s = 1/k_f + 1/k_c: what the data determine below the coupling's own signature, "
             + ("whatever the coupling" if stiff else "from the coupled fit"))
    bound = coupling_bound(frf, sdof, np.asarray(theta[:3], float), birge) if stiff else None
    if stiff and suspected is not None:
        checks.append(suspected)
        out["k_f"] = Estimate(
            None, None, kf.unit, False,
            "k_f of the transducer alone is not determined: the data contradict the stiff coupling it would rest on "
            f"(coupling_suspected: Eq. 9 misfits with chi2/dof {suspected.values['chi2_per_dof_stiff']:.3g}, a "
            f"coupling fits with {suspected.values['chi2_per_dof_coupled']:.3g}); the series stiffness "
            f"k_s = {k_s:.6g} N/m is in 'determined'")
        ib = "b_f"
        if out[ib].identifiable:
            out[ib] = _conditional(out[ib], "conditional on a stiff coupling, which the data contradict "
                                            "(coupling_suspected): the coupling's damping is in it too")
    elif bound is not None:
        u_k = float(kf.std or 0.0)
        k_hi = bound.k_f_high
        if bound.k_c_min is None:
            rng = "this plan would show any coupling softer than 1e6 k_s"
        elif k_hi is None:
            rng = (f"this plan cannot tell a coupling as soft as k_c = {bound.k_c_min:.3g} N/m "
                   f"({bound.k_c_min / k_s:.3g} k_s) from a stiff one, so k_f alone is not bounded above")
        else:
            rng = (f"this plan cannot tell a coupling k_c >= {bound.k_c_min:.3g} N/m ({bound.k_c_min / k_s:.3g} k_s) "
                   f"from a stiff one, so k_f alone lies in [{k_s:.6g}, {k_hi:.6g}] N/m "
                   f"(+{100 * (k_hi / k_s - 1):.2g} %)")
        determined["transducer_stiffness_alone"] = DeterminedQuantity(
            None, "N/m", range=(k_s, k_hi), bounds={"k_c_lower_bound_N_per_m": bound.k_c_min},
            conditional_on="a stiff coupling (k_c -> inf): " + rng)
        text = ("conditional on a stiff coupling (Eq. 9): the data determine the series stiffness of transducer "
                "and coupling; " + rng)
        width = np.inf if k_hi is None else k_hi - k_s
        soft = k_hi is None or (bound.k_c_min is not None and bound.k_c_min < ADAPTER_COUPLING_RATIO * k_s)
        if k_hi is None:
            out["k_f"] = Estimate(None, None, kf.unit, False, "k_f of the transducer alone is not determined: " + rng)
        elif soft and width > u_k:
            out["k_f"] = _conditional(kf, text)
        else:
            out["k_f"] = replace(kf, reason=(kf.reason + "; " if kf.reason else "") + text)
        if width > 3 * u_k:
            lead = ("k_f rests on a stiff coupling that this plan cannot confirm: " if soft else
                    "k_f rests on a stiff coupling; this plan excludes the soft ones, but not all that would move "
                    "k_f by more than 3 u: ")
            checks.append(Check("coupling_not_excluded", Severity.WARNING if soft else Severity.INFO, None,
                                lead + rng + f"; u(k_f) = {u_k:.3g} N/m; steps at higher frequencies narrow the range",
                                bound.to_dict()))
        ib = "b_f"
        bp = out[ib]
        if soft and bp.identifiable and bp.std is not None and (bound.b_f_high is None
                                                                or bound.b_f_high - bound.b_s > float(bp.std)):
            hi = "unbounded" if bound.b_f_high is None else f"up to {bound.b_f_high:.6g} N*s/m"
            out[ib] = _conditional(bp, f"conditional on a stiff coupling (Eq. 9): b_f alone {hi} under the "
                                       "couplings this plan cannot exclude (b_c = 0)")
    return StructureOutcome(out, tuple(checks), determined,
                            structure_statement(model_key, stiff, inputs, bound, suspected is not None))


def resonance_suspected(frf: frfmod.FrequencyResponse, sdof: SdofModel, theta: FloatArray, sdof_chi2: float,
                        sdof_dof: int) -> Check | None:
    """A finding when Eq. 9 misfits beyond the noise and a displacement-sensor resonance above the
    plan explains most of the misfit: Eq. 9 times 1/H_s(f; f_r, p) fitted with f_r, p free (from a
    few starts), named when its chi^2/dof is below half of Eq. 9's with f_r above the highest step
    and 0 <= p <= 10."""
    dof = 2 * frf.f_hz.size - 5
    if dof < 1 or sdof_dof < 1:
        return None
    from scipy.optimize import least_squares  # here: a report reads the structure without this fit

    W = frfmod.whiteners(frf.cov)
    f_max = float(np.max(frf.f_hz))

    def resid(q: FloatArray) -> FloatArray:
        th = theta * np.exp(q[:3])
        res = DisplacementResonance(f_max * float(np.exp(q[3])), float(np.exp(q[4])))
        d = sdof.response(th, frf.f_hz) / res.response(frf.f_hz) - frf.H
        r: FloatArray = np.einsum("fij,fj->fi", W, np.column_stack([d.real, d.imag])).ravel()
        return r

    best: tuple[float, FloatArray] | None = None
    for fr0, p0 in ((3.0, 0.3), (10.0, 0.5), (30.0, 1.0)):
        try:
            with np.errstate(all="ignore"):
                sol = least_squares(resid, np.array([0.0, 0.0, 0.0, np.log(fr0), np.log(p0)]), method="trf",
                                    max_nfev=400)
        except (ValueError, np.linalg.LinAlgError):
            continue
        chi2 = float(sol.fun @ sol.fun)
        if np.isfinite(chi2) and (best is None or chi2 < best[0]):
            best = (chi2, sol.x)
    if best is None:
        return None
    s2, c2 = sdof_chi2 / sdof_dof, best[0] / dof
    f_r, p = f_max * float(np.exp(best[1][3])), float(np.exp(best[1][4]))
    if not (c2 < 0.5 * s2 and f_r > f_max and p <= 10):
        return None
    return Check("displacement_resonance_suspected", Severity.WARNING, None,
                 f"Eq. 9 misfits the measured H(f) (chi2/dof {s2:.3g}) and a resonance of the displacement sensor "
                 f"explains it (f_r about {f_r:.3g} Hz, damping ratio about {p:.2g}: chi2/dof {c2:.3g}): state the "
                 "sensor's resonance in the measurement chain (displacement_resonance_hz, displacement_damping, "
                 "with their uncertainties) and identify again",
                 {"chi2_per_dof_flat": s2, "chi2_per_dof_resonance": c2, "resonance_hz": f_r, "damping": p})
