"""``identify_fd``: the frequency-domain estimator on a recording, with its inputs checked, its
assumptions stated and a GUM budget per parameter.

Flow: inputs (masses, chain: ``inputs``) -> plausibility gate and H(f) (``response.checked``, ``response.gate``) ->
start on 1/H -> weighted LM of the structurally identifiable parameters (Eq. 9, Eq. 8 when the
data demand and determine it) -> budget (``fd.budget``) -> per parameter: value with its combined
standard uncertainty; flag 'poorly_determined' when that is above ``Policy.max_rel_std`` of the
value; null only when the data cannot determine it (structurally, or relative uncertainty > 1);
flag 'conditional' when the end mass is assumed.  Reasons are computed at the estimate.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtri  # chi^2 quantiles without scipy.stats (0.6 s of CPU per worker start)

from station.ident.assumptions import Assumptions
from station.ident.fd.budget import Budget, uncertainty_budget
from station.ident.fd.core import fd_fit, start_values, summary_fd
from station.ident.identifiability import Policy, effect_text
from station.ident.inputs import IdentInputs, inputs_for
from station.ident.models import CoupledModel, Model, SdofModel, make_model
from station.ident.response import frf as frfmod
from station.ident.response.checked import CheckedResponse, checked_response
from station.ident.response.gate import sensitivity_check
from station.ident.response.redundancy import beside_clock_skew, static_check
from station.ident.result import Check, Estimate, IdentificationResult, estimated_covariance
from station.ident.structure import apply_structure, chain_corrected, coupling_suspected, resonance_suspected
from station.ident.uncertainty import DeterminedQuantity
from station.recording import Recording
from station.vocabulary import Flag, Severity

FloatArray = NDArray[np.float64]


def _single_frequency_reasons(model: Model, fit: frfmod.FrfFit, frf: frfmod.FrequencyResponse,
                              budget: Budget) -> dict[int, str]:
    """Reasons for S, k_f (and b_f) from one frequency, with the numbers at the estimate: b_f and S
    fitted to gain and phase with k_f held (the phase lag is b_f's effect whatever k_f is)."""
    th = frfmod.fit_frf(frf, model, fit.theta, free=np.array([True, False, True]), inflate=False).theta
    f = float(frf.f_hz[0])
    M = model.M
    q = float(np.abs(frf.H[0])) / M
    uq = q * float(budget.combined[0] / abs(fit.theta[0])) if np.isfinite(budget.combined[0]) else float("nan")
    ex = ", ".join(f"+{100 / (r * r - 1):.2g} % for a resonance at {r:g} f" for r in (10, 3))
    s_reason = (f"not identifiable from one frequency: {f:g} Hz determines |H|/M = {q:.6g} V/N (std {uq:.2g}), "
                f"which is HIGH against S by (f/f_0)^2 / (1 - (f/f_0)^2) below the resonance f_0 ({ex}); "
                "one frequency cannot tell that bias from S")
    struct = (f"structurally not identifiable: 1 sine frequency gives 2 real numbers (gain and phase) for "
              f"{len(model.names)} parameters")
    return {0: s_reason,
            1: struct + "; k_f is confounded with S: its effect on |H| is (f/f_0)^2 / (1 - (f/f_0)^2), "
                        "which one frequency cannot tell from S",
            2: struct + "; b_f is confounded with k_f (the phase lag fixes b_f / k_f only); "
                        + effect_text(model, th, frf.f_hz, 2)}


def _determined(model: Model, theta: FloatArray, budget: Budget) -> dict[str, DeterminedQuantity]:
    """What the data determine whatever the end mass: S M, the loaded natural frequency and the
    damping ratio (Eq. 9 depends on S M, k_f / M and b_f / M only)."""
    if not isinstance(model, SdofModel) or not budget.free[:2].all():
        return {}
    S, k, b = theta
    M = model.M
    out: dict[str, DeterminedQuantity] = {}
    inv = ("end_mass", "load_mass")  # exactly invariant: H depends on S M, k_f / M, b_f / M only
    sm = "V*s^2/m"
    out["S_times_M"] = DeterminedQuantity(float(S * M), sm, budget.budget_of(np.array([M, 0.0, 0.0]), sm, inv))
    f0 = np.sqrt(k / M) / (2 * np.pi)
    out["natural_frequency_hz"] = DeterminedQuantity(
        float(f0), "Hz", budget.budget_of(np.array([0.0, f0 / (2 * k), 0.0]), "Hz", inv))
    if budget.free[2]:
        # zeta = b / (2 sqrt(k M)) = (b/M) / (2 sqrt(k/M)): invariant too
        dz_db = 1 / (2 * np.sqrt(k * M))
        z = b * dz_db
        out["damping_ratio"] = DeterminedQuantity(
            float(z), "1", budget.budget_of(np.array([0.0, -z / (2 * k), dz_db]), "1", inv))
    return out


def _param_list(model: Model, theta: FloatArray, budget: Budget, rep_ok: tuple[bool, ...],
                reasons: list[str], inputs: IdentInputs, policy: Policy,
                frf: frfmod.FrequencyResponse) -> dict[str, Estimate]:
    out: dict[str, Estimate] = {}
    comb = budget.combined
    for i, (n, u) in enumerate(zip(model.names, model.units, strict=True)):
        if not budget.free[i] or not np.isfinite(comb[i]) or reasons[i].startswith("not identifiable from one"):
            out[n] = Estimate(None, None, u, False, reasons[i] or "held: not determined")
            continue
        rel = float(comb[i] / max(abs(theta[i]), 1e-300))
        parts = ", ".join(f"{s} {np.sqrt(c[i, i]) / max(abs(theta[i]), 1e-300):.2g}" for s, c in budget.covs.items()
                          if c is not None and c[i, i] > (0.01 * comb[i]) ** 2)
        if rel > 1:
            out[n] = Estimate(None, None, u, False, f"not determined by the data: relative "
                              f"uncertainty {rel:.2g} ({parts}); " + effect_text(model, theta, frf.f_hz, i))
            continue
        flag, reason = Flag.NONE, ""
        if rel > policy.max_rel_std or not rep_ok[i]:
            flag = Flag.POORLY_DETERMINED
            reason = (f"poorly determined: relative uncertainty {rel:.2g} (> {policy.max_rel_std}; {parts}); "
                      + effect_text(model, theta, frf.f_hz, i))
        if not inputs.end_mass_given and i < 3:
            flag = flag or Flag.CONDITIONAL
            reason = (reason + "; " if reason else "") + (
                f"conditional on the assumed end mass m_e = {inputs.m_e:g} kg (not given): "
                f"{'S' if i == 0 else n} scales as {'1/' if i == 0 else ''}(m_l + m_e)")
        out[n] = Estimate(float(theta[i]), float(comb[i]), u, True, reason, flag)
    return out


@dataclass(frozen=True)
class CouplingShown:
    """Whether the data exclude a rigid coupling: Eq. 8's chi^2 below Eq. 9's by more than the
    likelihood-ratio threshold for its two extra parameters (k_c, b_c) at ``COUPLING_P``."""

    delta_chi2: float
    threshold: float

    def __bool__(self) -> bool:
        return self.delta_chi2 > self.threshold

    @property
    def reason(self) -> str:
        return (f"not identifiable: the data do not exclude a rigid coupling (Eq. 8 lowers chi2 by "
                f"{self.delta_chi2:.3g} against Eq. 9, below the {self.threshold:.3g} that two more "
                f"parameters need at p = {COUPLING_P}); a local fit's k_c and its linearised u mean nothing then")


COUPLING_P = 0.0027  # 3 sigma, two-sided


def coupling_shown(chi2_stiff: float, chi2_coupled: float) -> CouplingShown:
    """The likelihood-ratio test of Eq. 8 against Eq. 9 (nested: k_c -> inf, b_c -> 0): a finite k_c
    is a result only where the data reject the rigid limit; where they do not, k_c at any value the
    optimiser stops at (e.g. 64 k_f with a 0.6 % linearised u on a rigid rig) is confidently wrong."""
    return CouplingShown(float(chi2_stiff - chi2_coupled), float(chdtri(2, COUPLING_P)))


def identify_fd(rec: Recording, model_key: str = "sdof", policy: Policy | None = None, *,
                inputs: IdentInputs | None = None, response: CheckedResponse | None = None) -> IdentificationResult:
    """Frequency-domain estimator with input checks, assumptions and budget (module docstring).

    model_key 'auto': Eq. 9, or Eq. 8 when Eq. 9 misfits (chi2/dof significantly > 1) and the
    coupled model determines k_c and S, k_f, b_f with it and fits (chi2/dof consistent with the noise);
    a coupled fit that leaves the transducer's parameters undetermined explains nothing, and would hide
    Eq. 9's misfit and the findings that name its cause."""
    inputs = inputs or inputs_for(rec)
    policy = replace(policy or Policy(), phase_floor_rad=inputs.chain.floor_phase_rad,
                     gain_floor=inputs.chain.floor_gain)
    cr = response if response is not None else checked_response(rec, inputs)
    frf, checks, notes = chain_corrected(cr.frf, inputs.chain), list(cr.checks), []
    if frf is not cr.frf:
        notes.append(f"H(f) corrected for the stated displacement-sensor resonance "
                     f"({inputs.chain.displacement_resonance_hz:g} Hz, damping {inputs.chain.displacement_damping:g})")
    sdof = make_model("sdof", inputs.m_e, inputs.m_l)
    assert isinstance(sdof, SdofModel)
    fit, rep = fd_fit(frf, sdof, start_values(frf, sdof, cr.sign), policy)
    sdof_fit = fit
    cfit: frfmod.FrfFit | None = None
    model: Model = sdof
    auto = model_key == "auto"
    if model_key in ("coupled", "h1") or (auto and fit.inflated and inputs.end_mass_given):
        cm = make_model("coupled", inputs.m_e, inputs.m_l)
        assert isinstance(cm, CoupledModel)
        th0 = np.r_[fit.theta, 10 * fit.theta[1], 0.1 * fit.theta[2]]
        cfit, crep = fd_fit(frf, cm, th0, policy)
        c2, s2 = cfit.chi2 / max(cfit.dof, 1), fit.chi2 / max(fit.dof, 1)
        shown = coupling_shown(fit.chi2, cfit.chi2)
        if crep.identifiable[3] and not shown:
            crep = replace(crep, identifiable=(*crep.identifiable[:3], False, False), reasons=(
                *crep.reasons[:3], shown.reason, "b_c is meaningless without k_c"))
        determines = crep.identifiable[3] and (not auto or all(crep.identifiable[:3]))
        if determines and (not auto or (c2 < 0.25 * s2 and not cfit.inflated)):
            if auto:
                notes.append(f"model chosen: coupled (Eq. 8), chi2/dof {c2:.3g} against {s2:.3g} for Eq. 9")
            fit, rep, model = cfit, crep, cm
        elif auto:
            notes.append(f"Eq. 9 misfits (chi2/dof {s2:.3g}) but the coupled model does not determine k_c "
                         "either; unmodelled effects (conditioner filter, channel delay) are likely")
        else:
            notes.append("k_c not identifiable: S, k_f, b_f are given in the stiff-coupling "
                         "limit (Eq. 9, k_c -> inf, b_c -> 0)")
            model = cm
            cov = np.zeros((5, 5))
            cov[:3, :3] = fit.cov
            fit = replace(fit, theta=np.r_[fit.theta, cfit.theta[3:]], cov=cov)
            rep = replace(crep, identifiable=(*rep.identifiable, False, False),
                          reasons=(*rep.reasons[:3], crep.reasons[3] or "k_c not identifiable",
                                   crep.reasons[4] or "b_c is meaningless without k_c"))
    if cfit is None and sdof_fit.inflated and inputs.end_mass_given and sdof_fit.dof > 2:
        cm = make_model("coupled", inputs.m_e, inputs.m_l)
        cfit = fd_fit(frf, cm, np.r_[sdof_fit.theta, 10 * sdof_fit.theta[1], 0.1 * sdof_fit.theta[2]], policy)[0]
    stiff = isinstance(model, SdofModel) or not rep.identifiable[3]
    suspected = None
    if stiff and sdof_fit.inflated and cfit is not None:
        suspected = coupling_suspected(frf, sdof_fit.chi2, sdof_fit.dof, cfit.theta, cfit.chi2, cfit.dof)
    if stiff and sdof_fit.inflated and inputs.chain.displacement_resonance is None:
        sensor = resonance_suspected(frf, sdof, sdof_fit.theta, sdof_fit.chi2, sdof_fit.dof)
        checks += [sensor] if sensor else []
    free = np.diag(fit.cov) > 0
    free[3:] &= np.array(rep.identifiable[3:], bool)
    budget = uncertainty_budget(model, fit.theta, fit.cov, frf, free, inputs,
                                noise_dof=float(fit.dof) if fit.inflated else None)
    reasons = list(rep.reasons)
    n_f = int(np.unique(np.round(frf.f_hz, 6)).size)
    if n_f == 1 and isinstance(model, SdofModel):
        reasons = [_single_frequency_reasons(model, fit, frf, budget)[i] for i in range(3)]
    if fit.inflated:
        notes.append(f"chi2/dof = {fit.chi2 / fit.dof:.3g}: uncertainties inflated by sqrt(chi2/dof)")
        checks.append(Check("model_misfit", Severity.WARNING, None, f"the model misfits the measured H(f): chi2/dof "
                            f"{fit.chi2 / fit.dof:.3g}; noise uncertainties inflated by its square root",
                            {"chi2_per_dof": fit.chi2 / fit.dof}))
    params = _param_list(model, fit.theta, budget, rep.identifiable, reasons, inputs, policy, frf)
    birge = sdof_fit.chi2 / sdof_fit.dof if sdof_fit.inflated else 1.0
    structure = apply_structure(model.key, stiff, params, fit.theta, budget, frf, sdof, birge, inputs, suspected)
    params = structure.parameters
    checks = beside_clock_skew(checks + list(structure.checks))
    c = sensitivity_check(params["S"].value, rec.sensitivity_V_per_N, not inputs.end_mass_given)
    checks += [c] if c else []
    c = static_check(cr.force_offsets, params["S"], inputs.m_e + inputs.m_l, rec.config,
                     any(x.name == "displacement_vs_radius" for x in checks))
    checks += [c] if c else []
    determined = {**_determined(model, fit.theta, budget), **structure.determined}
    if n_f == 1 and budget.free[0]:
        determined["quasi_static_sensitivity"] = DeterminedQuantity(
            float(cr.sign * np.abs(frf.H[0]) / model.M), "V/N", budget.budget_of(np.eye(len(fit.theta))[0], "V/N"),
            note="|H|/M at the one frequency: S only far below the resonance, HIGH by "
                 "(f/f_0)^2 / (1 - (f/f_0)^2) otherwise")
    if not inputs.end_mass_given:
        checks.append(Check("end_mass_not_given", Severity.WARNING, None, "the end mass is not given: S, k_f, b_f are "
                            f"conditional on an assumed m_e = {inputs.m_e:g} kg; the data determine S (m_l + m_e), "
                            "the loaded natural frequency and the damping ratio (see 'determined')",
                            {"assumed_end_mass_kg": inputs.m_e}))
    extra = {"cost_history": list(fit.history), "dof": fit.dof,
             "m_e_kg": model.m_e, "m_l_kg": model.m_l, "f_hz": frf.f_hz.tolist(), "H_abs": np.abs(frf.H).tolist(),
             "H_phase_rad": np.angle(frf.H).tolist(),
             "H_std": np.sqrt(np.trace(frf.cov, axis1=1, axis2=2) / 2).tolist(), "steps_used": cr.used}
    return IdentificationResult("fd", model.key, params, summary_fd(frf, fit, cr.sigs), rep,
                                tuple(notes), extra, tuple(checks), budget.uncertainty(),
                                Assumptions.of(inputs, structure.statement), determined,
                                estimated_covariance(params, model.names, budget.cov))
