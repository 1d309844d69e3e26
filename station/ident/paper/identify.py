"""The paper's estimators on a recording: PSO/PSO+ on Eq. 10/11 and RLS on Eq. 17 (Section 5).

Digital coefficients are mapped to physical parameters with the known masses (models.from_digital,
as the paper does for Cases III and V).  The swarm gives no uncertainty; we attach the covariance
and the identifiability decision of what the record carries: gain and phase of H at one sine
frequency, i.e. at most two real parameters (``identifiability.assess``).

A swarm's answer is a draw: a parameter is called identifiable only when it is also

* stable against the swarm seed: the swarm is run again with the fixed seeds ``STABILITY_SEEDS``
  (besides the caller's; only when the caller's run has a verdict to confirm), and every run must
  give it within 3 standard uncertainties of the reported value (so that the verdict, and the
  answer up to its uncertainty, do not depend on the seed asked for);
* physically plausible in every run: positive stiffnesses, non-negative dampings, and for Eq. 10
  a coupling not far softer than the transducer (``structure.plausible_coupling``).

* stated with an uncertainty that is not conditional on what the step does not determine: the swarm
  states no uncertainty of the parameters one frequency leaves undetermined, so a parameter that
  depends on them at fixed H(f) is withheld (``identifiability.carried_to_determined``; RLS carries
  its own covariance of them instead, ``rls_uncertainty``).

Otherwise it is withheld with the reason.  The swarm itself (Eq. 12-16, Section 5.1 settings) is
as published; the value reported is the caller's seed's.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from station.ident.identifiability import Policy, assess, carried_to_determined
from station.ident.models import DigitalTF, Model
from station.ident.paper.protocol import PUBLISHED_SWARM, PaperData, PaperProtocol, SwarmSize, paper_data, testing_mse
from station.ident.paper.pso import SECTION5_H1, SECTION5_H2, PsoResult, PsoSettings, identify_digital
from station.ident.paper.rls import RlsResult, rls_h2
from station.ident.paper.rls_uncertainty import DYNAMICS_TERM, NOISE_TERM, rls_uncertainty
from station.ident.response.frf import FrequencyResponse, ratio_cov, whitened_jacobian
from station.ident.response.sinefit import fit3
from station.ident.result import (
    FitSummary,
    Identifiability,
    IdentificationResult,
    JsonValue,
    estimated_covariance,
    estimates,
)
from station.ident.structure import MIN_PLAUSIBLE_COUPLING_RATIO, plausible_coupling
from station.ident.uncertainty import ParameterBudget, UncertaintyBudget
from station.kept import Kept, content_key
from station.recording import Recording

FloatArray = NDArray[np.float64]
DEFAULT_POLICY = Policy()
DEFAULT_PROTOCOL = PaperProtocol()
STABILITY_SEEDS = (0, 1, 2)
# the last few swarm runs, (b, a, result) of identify_digital: the stability seeds are shared
_SWARMS: Kept[tuple[FloatArray, FloatArray, PsoResult]] = Kept(16, lambda run: run)


def _swarm(form: str, data: PaperData, settings: PsoSettings,
           seed: int) -> tuple[FloatArray, FloatArray, PsoResult]:
    """identify_digital, remembered for the last 16 (form, settings, seed, data) in this process."""
    key = content_key(data.x_id, data.y_id, settings=(form, settings, seed, data.T))
    return _SWARMS.get(key, lambda: identify_digital(form, data.x_id, data.y_id, settings, seed))


def _physical(form: str, theta: FloatArray) -> str:
    """'' when theta is a parameter set a rig can have, else why not."""
    if not np.all(np.isfinite(theta)):
        return "the coefficients do not map to finite physical parameters"
    if theta[1] <= 0 or theta[2] < 0:
        return f"non-physical: k_f = {theta[1]:.3g} N/m, b_f = {theta[2]:.3g} N*s/m"
    if form == "h1" and not plausible_coupling(theta):
        return (f"non-physical: k_c = {theta[3]:.3g} N/m = {theta[3] / theta[1]:.2g} k_f, b_c = {theta[4]:.3g} N*s/m "
                f"(no coupling is more than {1 / MIN_PLAUSIBLE_COUPLING_RATIO:g} times softer than the transducer)")
    return ""


def seed_stability(form: str, theta: FloatArray, std: FloatArray, others: dict[int, FloatArray],
                   names: tuple[str, ...]) -> list[str]:
    """Per parameter, '' when every other swarm run gives a physical answer within 3 std of theta."""
    out = [""] * theta.size
    bad_runs = {s: why for s, th in others.items() if (why := _physical(form, th))}
    for i in range(theta.size):
        if bad_runs:
            s0, why = next(iter(bad_runs.items()))
            out[i] = f"not stable against the swarm seed: seed {s0} gives a {why.split(':')[0]} answer ({why})"
            continue
        off = {s: th[i] for s, th in others.items() if not abs(th[i] - theta[i]) <= 3 * std[i]}
        if off:
            vals = ", ".join(f"seed {s}: {v:.4g}" for s, v in sorted(off.items()))
            out[i] = (f"not stable against the swarm seed: {names[i]} = {theta[i]:.4g} +- {std[i]:.2g} here, "
                      f"but {vals} (beyond 3 standard uncertainties)")
    return out


def step_frf(data: PaperData) -> FrequencyResponse:
    """H at the step frequency from three-parameter sine fits of the identification window
    (input: acceleration phasor, output: force phasor)."""
    t = np.arange(data.x_id.size) * data.T
    fa = fit3(np.asarray(t, dtype=np.float64), data.x_id, data.f_hz)
    fu = fit3(np.asarray(t, dtype=np.float64), data.y_id, data.f_hz, t_center_s=fa.t_center_s)
    H, C = ratio_cov(fu.phasor, fu.phasor_cov, fa.phasor, fa.phasor_cov)
    return FrequencyResponse(np.array([data.f_hz]), np.array([H]), C[None], np.array([fu.residual_rms]),
                             np.array([fu.offset]))


def steady_state_uncertainty(model: Model, theta: FloatArray, data: PaperData,
                             policy: Policy) -> tuple[FloatArray, Identifiability]:
    """Covariance and identifiability of theta judged on what the record carries in steady state:
    gain and phase of H at the one step frequency (the zero-initial-condition transient of Eq. 15
    is an artefact of the fitting, not information about the transducer)."""
    frf = step_frf(data)
    rep, ok = assess(model, theta, frf, policy)
    cov = np.zeros((theta.size, theta.size))
    if ok.any():
        J = whitened_jacobian(model, theta, frf)[:, ok]
        cov[np.ix_(ok, ok)] = np.linalg.pinv(J.T @ J) * np.outer(theta[ok], theta[ok])
    reasons = list(rep.reasons)
    for i in range(theta.size):
        if not np.isfinite(theta[i]) or theta[i] <= 0:
            reasons[i] = (reasons[i] + "; " if reasons[i] else "") + (
                f"the coefficients map to a non-physical value ({theta[i]:.4g})")
    return cov, replace(rep, identifiable=tuple(r == "" for r in reasons), reasons=tuple(reasons))


def withhold_unstated(rep: Identifiability, cov: FloatArray, names: tuple[str, ...]) -> Identifiability:
    """A determined parameter whose stated covariance is not finite is withheld: its uncertainty
    rests on parameters the step does not determine, and the estimator gives no uncertainty of
    them (``identifiability.carried_to_determined``); the noise-only u would understate it."""
    others = ", ".join(n for n, ok in zip(names, rep.identifiable, strict=True) if not ok)
    reasons = [r or (f"withheld: its uncertainty rests on {others}, which one frequency does not determine "
                     "and the estimator states no uncertainty of (the noise of the step alone would "
                     "understate it)" if not np.isfinite(cov[i, i]) else "")
               for i, r in enumerate(rep.reasons)]
    return replace(rep, identifiable=tuple(r == "" for r in reasons), reasons=tuple(reasons))


def _rls_budget(model: Model, theta: FloatArray, data: PaperData, r: RlsResult, cov_noise: FloatArray,
                rep: Identifiability, extra: dict[str, JsonValue]) -> tuple[FloatArray, dict[str, dict[str, float]]]:
    """The covariance the station states for RLS: the steady-state noise term plus
    ``unidentified_dynamics`` (``rls_uncertainty``), and the two terms' standard uncertainties per
    parameter (the budget's contributions); the estimator's own std and the lags go to ``extra``."""
    unc = rls_uncertainty(model, theta, data, r, step_frf(data), rep.identifiable)
    cov = cov_noise + unc.cov_dynamics
    terms = {n: {NOISE_TERM: float(np.sqrt(max(cov_noise[i, i], 0.0))),
                 DYNAMICS_TERM: float(np.sqrt(max(unc.cov_dynamics[i, i], 0.0)))}
             for i, n in enumerate(model.names) if rep.identifiable[i]}
    extra["rls_estimator_std"] = {n: float(np.sqrt(max(unc.cov_estimator[i, i], 0.0)))
                                  for i, n in enumerate(model.names)}
    extra["newey_west_lags"] = unc.lags
    return cov, terms


def identify_paper_method(rec: Recording, method: str, form: str, model: Model, *, seed: int = 0,
                          protocol: PaperProtocol = DEFAULT_PROTOCOL,
                          policy: Policy = DEFAULT_POLICY, swarm: SwarmSize = PUBLISHED_SWARM) -> IdentificationResult:
    """PSO / PSO+ (form 'h2' = Eq. 11 or 'h1' = Eq. 10) or RLS (Eq. 17) on one step of ``rec``;
    the swarm's answer is checked for stability and plausibility (module docstring).  ``swarm``:
    another size than Section 5.1's (quick checks)."""
    data = paper_data(rec, protocol)
    extra: dict[str, JsonValue] = {"step_index": data.step_index, "f_hz": data.f_hz, "T_s": data.T, "form": form}
    terms: dict[str, dict[str, float]] = {}
    others: dict[int, FloatArray] = {}
    settings = swarm.applied(replace(SECTION5_H2 if form == "h2" else SECTION5_H1,
                                     variant="pso+" if method == "pso+" else "pso"))
    rls: RlsResult | None = None
    if method == "rls":
        rls = rls_h2(data.x_id, data.y_id)
        b, a = rls.b, rls.a
    else:
        b, a, pres = _swarm(form, data, settings, seed)
        extra.update(seed=seed, iterations_to_converge=pres.iterations_to_converge,
                     n_particles=settings.n_particles, n_iterations=settings.n_iterations,
                     mse_history=pres.mse_history[:: max(1, settings.n_iterations // 200)].tolist())
    extra.update(b=b.tolist(), a=a.tolist(), testing_mse_V2=testing_mse(b, a, data))
    with np.errstate(all="ignore"):
        theta = model.from_digital(DigitalTF(b, a, data.T))
        res = lfilter(b, a, data.x_id) - data.y_id
    mse = float(np.mean(res**2))
    extra["theta_from_coefficients"] = [float(v) for v in theta]
    if np.all(np.isfinite(theta)):
        cov, rep = steady_state_uncertainty(model, theta, data, policy)
        if rls is not None:
            cov, terms = _rls_budget(model, theta, data, rls, cov, rep, extra)
        else:  # the swarm states no uncertainty of what the step leaves undetermined
            cov = cov + carried_to_determined(model, theta, step_frf(data), rep.identifiable,
                                              np.full_like(cov, np.nan))
        if not _physical(form, theta):  # a non-physical answer is withheld as such (below)
            rep = withhold_unstated(rep, cov, model.names)
        cov = np.where(np.isfinite(cov), cov, 0.0)
    else:
        cov = np.full((theta.size, theta.size), np.nan)
        rep = Identifiability(model.names, float("inf"), (), (False,) * theta.size,
                              ("coefficients do not map to physical parameters",) * theta.size)
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    why = _physical(form, theta) if np.all(np.isfinite(theta)) else ""
    if method != "rls" and not why and any(rep.identifiable):  # only a verdict to confirm costs reruns
        for s in STABILITY_SEEDS:
            if s != seed:
                bs, as_, _ = _swarm(form, data, settings, s)
                with np.errstate(all="ignore"):
                    others[s] = model.from_digital(DigitalTF(bs, as_, data.T))
        extra["stability_seeds"] = sorted(others)
        extra["theta_other_seeds"] = {str(k): [float(v) for v in th] for k, th in others.items()}
    unstable = seed_stability(form, theta, std, others, model.names) if others else [""] * theta.size
    reasons = [r or (why and f"withheld: the answer is {why}") or unstable[i] if rep.identifiable[i] else r
               for i, r in enumerate(rep.reasons)]
    rep = replace(rep, identifiable=tuple(r == "" for r in reasons), reasons=tuple(reasons))
    params = estimates(model.names, model.units, theta, cov, rep.identifiable, rep.reasons)
    summary = FitSummary(mse, (float(np.sqrt(mse)),), float("nan"), int(data.x_id.size))
    notes = (f"paper protocol (Section 5.1) on step {data.step_index} ({data.f_hz:g} Hz): resampled to "
             f"{1 / data.T:g} Hz, {data.x_id.size} identification and {data.x_test.size} test points",)
    budget = UncertaintyBudget({n: ParameterBudget.of(terms.get(n) or {NOISE_TERM: p.std}, p.std, p.unit)
                                for n, p in params.items() if p.identifiable and p.std is not None})
    return IdentificationResult(method, form, params, summary, rep, notes, extra, budget=budget,
                                covariance=estimated_covariance(params, model.names, cov))
