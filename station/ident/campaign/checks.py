"""The named checks of a multi-mass campaign (``campaign.identify``), their thresholds
(``CampaignPolicy``) and the campaign's uncertainty budget.

* ``end_mass_separation``: can the load masses separate S from m_e?  From the combined covariance
  of (S, m_e, k_f, b_f) (noise, load masses, measurement chain: ``campaign_budget``), the relative
  standard uncertainty of S and the standard uncertainty of m_e at the estimate (they go together:
  S (m_e + m_l) is what one mass fixes, so u(S)/S ~ u(m_e)/M).
* ``same_transducer_model``: S and k_f of each recording's own Eq. 9 fit, m_e held at the campaign's,
  must agree (chi^2 about the weighted mean, chi^2 distribution's p-value).
* ``campaign_budget``: noise, load masses, end mass (conditional case), measurement chain.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtrc  # the chi^2 tail without scipy.stats (0.6 s of CPU per worker start)

from station.config import MeasurementChain
from station.ident.campaign import jointfit as jf
from station.ident.fd.budget import resonance_vectors
from station.ident.models import SdofModel
from station.ident.response.frf import FrequencyResponse, fit_frf
from station.ident.result import Check, JsonValue
from station.ident.uncertainty import Covariance, ParameterBudget, UncertaintyBudget
from station.recording import Recording
from station.vocabulary import Severity

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class CampaignPolicy:
    """Decision thresholds.  distinct_sigma: load masses closer than this many combined standard
    uncertainties count as one; max_S_rel_std, poor_S_rel_std: relative standard uncertainty of S
    (measurement chain included) above which S and m_e are refused / flagged as poorly separated;
    consistency_p_warn, consistency_p_refuse: p-values of the consistency tests (warning / refusal)."""

    distinct_sigma: float = 3.0
    max_S_rel_std: float = 0.01
    poor_S_rel_std: float = 1e-3
    consistency_p_warn: float = 1e-3
    consistency_p_refuse: float = 1e-6


def own_fits(frfs: list[FrequencyResponse], priors: list[jf.MassPrior], theta: FloatArray) -> list[FloatArray]:
    """Per recording (S, k_f, b_f, std S, std k_f) of its own Eq. 9 fit with m_e held at theta[1]; the
    standard uncertainties include the recording's load-mass uncertainty (S, k_f scale with 1/M, M)."""
    out = []
    for frf, pr in zip(frfs, priors, strict=True):
        model = SdofModel(float(theta[1]), pr.value)
        th0 = np.array([theta[0], theta[2], theta[3]])
        fit = fit_frf(frf, model, th0, inflate=False)
        sd = np.sqrt(np.clip(np.diag(fit.cov), 0, None))
        rel_m = pr.std / model.M  # a load-mass error scales this recording's S and k_f (not the others')
        out.append(np.r_[fit.theta, np.hypot(sd[:2], rel_m * np.abs(fit.theta[:2]))])
    return out


def _homogeneity(vals: FloatArray, sds: FloatArray) -> tuple[float, int, float]:
    """chi^2 of values about their weighted mean, dof, p-value."""
    w = 1.0 / sds**2
    mean = float(np.sum(w * vals) / np.sum(w))
    chi2 = float(np.sum(w * (vals - mean) ** 2))
    dof = vals.size - 1
    return chi2, dof, float(chdtrc(dof, chi2)) if dof else 1.0  # chi2.sf(chi2, dof); one value: no spread


def consistency(recs: list[Recording], own: list[FloatArray], policy: CampaignPolicy) -> Check | None:
    if len(own) < 2:
        return None
    o = np.array(own)
    res = {}
    for name, i, j in (("S", 0, 3), ("k_f", 1, 4)):
        res[name] = _homogeneity(o[:, i], np.maximum(o[:, j], 1e-300))
    p = min(r[2] for r in res.values())
    vals: dict[str, JsonValue] = {f"{n}_chi2": r[0] for n, r in res.items()}
    vals |= {f"{n}_p": r[2] for n, r in res.items()}
    vals |= {"dof": res["S"][1], "S_per_recording": o[:, 0].tolist(), "k_f_per_recording": o[:, 1].tolist()}
    txt = "; ".join(f"{n} chi2 {r[0]:.3g} on {r[1]} dof (p {r[2]:.2g})" for n, r in res.items())
    if p >= policy.consistency_p_warn:
        return Check("same_transducer_model", Severity.INFO, None,
                     f"one Eq. 9 transducer explains every top mass: {txt}", vals)
    sev = Severity.REFUSED if p < policy.consistency_p_refuse else Severity.WARNING
    return Check("same_transducer_model", sev, None,
                   f"S and k_f of the recordings' own fits disagree beyond their uncertainties ({txt}); the "
                   "recordings are not one Eq. 9 transducer with these top masses (a mistyped top mass, a "
                   "changed set-up, or an effect Eq. 9 lacks: coupling, conditioner filter, channel delay; "
                   "`station discrepancy` on each recording names it)", vals)


def campaign_budget(frfs: list[FrequencyResponse], priors: list[jf.MassPrior], fit: jf.JointFit, separated: bool,
                    chain: MeasurementChain, m_e_prior: jf.MassPrior | None) -> tuple[FloatArray, UncertaintyBudget]:
    """Covariance (4, 4) of (S, m_e, k_f, b_f) and the GUM budget per parameter with each source's
    covariance over the budgeted parameters (sources as the
    single-recording ``fd.budget``).  noise, load_mass and (conditional case) end_mass: the Fisher
    information built up term by term (each contribution the covariance it adds; the noise term
    Birge-scaled when the fit was inflated).  chain_gain, chain_phase, chain_delay, chain_resonance:
    sensitivity coefficients
    (``jointfit.data_sensitivity``), the recordings sharing one measurement chain: the gain ratio,
    phase offset and delay are common to every step of every recording, flatness and per-frequency
    phase independent from step to step.  radius: 0 (the measured displacement is the input)."""
    scale = np.r_[fit.scale, [max(p.value, 1e-3) for p in priors]]
    p = np.r_[fit.theta, fit.load_mass]
    exact = [jf.MassPrior(pr.value, 0.0) for pr in priors]
    birge = fit.chi2_per_dof if fit.inflated else 1.0
    cond_me = not separated and m_e_prior is not None and m_e_prior.std > 0
    stages: list[tuple[str, list[jf.MassPrior], bool]] = [("noise", exact, False), ("load_mass", priors, False)]
    if cond_me:
        stages.append(("end_mass", priors, True))
    covs: dict[str, FloatArray] = {}
    prev = np.zeros((4, 4))
    for name, prs, with_me in stages:
        F = jf.fisher_relative(frfs, prs, p, scale, None)
        free = np.ones(4, bool)
        if not separated:
            if with_me and m_e_prior is not None:
                F[1, 1] += (scale[1] / m_e_prior.std) ** 2
            else:
                free[1] = False
        cov = np.zeros((4, 4))
        cov[np.ix_(free, free)] = np.linalg.pinv(F[np.ix_(free, free)])
        cov *= np.outer(fit.scale, fit.scale)
        covs[name] = (cov - prev) * (birge if name == "noise" else 1.0)
        prev = cov
    free4 = np.array([True, separated, True, True])
    sens = jf.data_sensitivity(frfs, priors, p, scale, free4, m_e_prior.std if cond_me and m_e_prior else None)
    Hs = [f.H for f in frfs]

    def spread(vectors: list[tuple[list[NDArray[np.complex128]], float]]) -> FloatArray:
        out = np.zeros((4, 4))
        for v, sd in vectors:
            d = sens(v) * sd
            out += np.outer(d, d)
        return out

    def points(fn: Any) -> list[list[NDArray[np.complex128]]]:
        res = []
        for r, H in enumerate(Hs):
            for k in range(H.size):
                v = [np.zeros_like(h) for h in Hs]
                v[r][k] = fn(H)[k]
                res.append(v)
        return res

    covs["chain_gain"] = spread([(Hs, chain.gain_rel_std)] + [(v, chain.flatness_rel_std) for v in points(lambda H: H)])
    covs["chain_phase"] = spread([([1j * H for H in Hs], np.deg2rad(chain.phase_offset_std_deg))]
                                 + [(v, np.deg2rad(chain.phase_std_deg)) for v in points(lambda H: 1j * H)])
    covs["chain_delay"] = spread([([2j * np.pi * f.f_hz * f.H for f in frfs], chain.delay_std_s)])
    # the displacement sensor's resonance (one sensor for every recording: correlated across them)
    per_rec = [resonance_vectors(f.H, f.f_hz, chain) for f in frfs]
    covs["chain_resonance"] = spread([([v[j][0] for v in per_rec], per_rec[0][j][1])
                                      for j in range(len(per_rec[0]))] if per_rec else [])
    covs["radius"] = np.zeros((4, 4))
    total = np.asarray(sum(covs.values()))
    budget: dict[str, ParameterBudget] = {}
    for i, (n, u) in enumerate(zip(jf.NAMES, jf.UNITS, strict=True)):
        if not free4[i]:
            continue
        budget[n] = ParameterBudget.of({k: float(np.sqrt(max(c[i, i], 0.0))) for k, c in covs.items()},
                                       float(np.sqrt(max(total[i, i], 0.0))), u)
    idx = np.nonzero(free4)[0]
    names, units = [jf.NAMES[i] for i in idx], [jf.UNITS[i] for i in idx]
    per_source = {k: Covariance.of(names, units, c[np.ix_(idx, idx)]) for k, c in covs.items()}
    return total, UncertaintyBudget(budget, per_source)


def separation(fit: jf.JointFit, cov: FloatArray, priors: list[jf.MassPrior], policy: CampaignPolicy) -> Check:
    """``end_mass_separation`` from the combined covariance (noise, load masses, chain) of a joint fit
    with m_e free; condition number of the Fisher information in relative units."""
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    ev = np.linalg.eigvalsh(fit.fisher_rel)
    cond = float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 0 else float("inf")
    rel_S, u_me = float(sd[0] / abs(fit.theta[0])), float(sd[1])
    corr = float(cov[0, 1] / (sd[0] * sd[1])) if sd[0] * sd[1] > 0 else float("nan")
    ms = [pr.value for pr in priors]
    spread = float(np.ptp(ms))
    needed = spread * rel_S / policy.poor_S_rel_std  # u(S) scales as 1 / (mass spread)
    vals: dict[str, JsonValue] = {
            "load_masses_kg": ms, "mass_spread_kg": spread, "S_rel_std": rel_S, "m_e_std_kg": u_me,
            "S_m_e_correlation": corr, "condition_number": cond, "max_S_rel_std": policy.max_S_rel_std,
            "poor_S_rel_std": policy.poor_S_rel_std, "spread_needed_kg": needed}
    txt = (f"load masses {', '.join(f'{m:.6g}' for m in ms)} kg (spread {spread:.3g} kg) determine S to "
           f"{rel_S:.2g} (relative) and m_e to {u_me:.2g} kg, measurement chain included (S-m_e correlation "
           f"{corr:.4f}, condition number {cond:.3g})")
    if rel_S > policy.max_S_rel_std:
        return Check("end_mass_separation", Severity.REFUSED, None,
                     f"the top masses are too alike to separate S from m_e: {txt}; a spread of about "
                     f"{needed:.3g} kg would give S to {policy.poor_S_rel_std:g}", vals)
    if rel_S > policy.poor_S_rel_std:
        return Check("end_mass_separation", Severity.WARNING, None,
                     f"S and m_e are separated, but poorly: {txt}; a spread of about {needed:.3g} kg would "
                     f"give S to {policy.poor_S_rel_std:g}", vals)
    return Check("end_mass_separation", Severity.INFO, None, f"S and m_e separated: {txt}", vals)


def odd_one_out(frfs: list[FrequencyResponse], priors: list[jf.MassPrior], recs: list[Recording],
                theta: FloatArray) -> tuple[str, float] | None:
    """The recording whose removal lowers the joint chi^2/dof most (leave one out), and that chi^2/dof;
    None with fewer than four recordings: G_r = S M_r and w_r^2 = k_f / M_r fix the M_r up to one
    scale, so two recordings fit any two stated masses and a mistyped mass shows only from three on,
    and which one it is only from four on."""
    if len(frfs) < 4:
        return None
    best: tuple[str, float] | None = None
    for k in range(len(frfs)):
        fk = [f for i, f in enumerate(frfs) if i != k]
        pk = [p for i, p in enumerate(priors) if i != k]
        if np.ptp([p.value for p in pk]) <= 0:
            continue
        fit = jf.fit_joint(fk, pk, jf.start_values(fk, pk, float(theta[1])))
        if best is None or fit.chi2_per_dof < best[1]:
            best = (recs[k].path.name, fit.chi2_per_dof)
    return best


def end_mass_plausibility(fit: jf.JointFit, std_m_e: float, stated: jf.MassPrior | None,
                          n_distinct: int) -> list[Check]:
    """Checks of a separated m_e: not negative, consistent with a stated end mass, and whether the
    masses check each other (with two distinct masses any error of theirs goes into m_e)."""
    out = []
    m_e = float(fit.theta[1])
    if m_e < -3 * std_m_e:
        out.append(Check("end_mass_negative", Severity.WARNING, None, f"the campaign's end mass {m_e:.4g} kg (std "
                           f"{std_m_e:.2g}) is negative: a stated top mass is likely wrong",
                           {"m_e_kg": m_e, "std_kg": std_m_e}))
    if stated is not None:
        z = (m_e - stated.value) / float(np.hypot(std_m_e, stated.std))
        sev = Severity.WARNING if abs(z) > 3 else Severity.INFO
        out.append(Check("end_mass_stated", sev, None, f"the campaign's end mass {m_e:.4g} kg (std {std_m_e:.2g}) "
                           f"{'differs from' if sev == 'warning' else 'agrees with'} the stated {stated.value:g} kg "
                           f"(std {stated.std:.2g}): z = {z:.2f}", {"z": float(z), "stated_kg": stated.value}))
    if n_distinct == 2:
        out.append(Check("mass_redundancy", Severity.INFO, None, "two distinct top masses: they fix S and m_e "
                           "exactly, so an error of a stated top mass goes into m_e unseen; a third mass would "
                           "check them",
                           {"distinct": n_distinct}))
    return out
