"""``identify_recording(rec, method, model)``: one entry point for every estimator.

Methods: 'fd' (sine fits per step -> H(f) -> linear start on 1/H -> weighted LM; default),
'oe' (time-domain output error), and the paper's 'pso', 'pso+' (Eq. 12-16) and 'rls' (Eq. 17)
on one step cut as in Section 5.1.  Models: 'sdof' (Eq. 9), 'coupled' (Eq. 8), and for the paper's
digital forms 'h2' (Eq. 11, maps to sdof) and 'h1' (Eq. 10, maps to coupled).
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from station.errors import BadInputError
from station.ident import frf as frfmod
from station.ident.identifiability import Policy, assess, correlations
from station.ident.models import CoupledModel, Model, SdofModel, make_model
from station.ident.oe import StepSignal, fit_oe
from station.ident.paperfit import identify_paper_method
from station.ident.protocol import PaperProtocol
from station.ident.result import FitSummary, Identifiability, IdentificationResult, ParameterEstimate
from station.recording import Recording, write_results

FloatArray = NDArray[np.float64]
METHODS = ("fd", "oe", "pso", "pso+", "rls")
MODELS = ("sdof", "coupled", "h1", "h2")
log = logging.getLogger(__name__)
DEFAULT_POLICY = Policy()
DEFAULT_PROTOCOL = PaperProtocol()


def model_for(rec: Recording, key: str) -> Model:
    """The model with the recording's masses (m_l load mass, m_e end mass; 0 if unknown for sdof)."""
    if rec.end_mass_kg is None and key in ("coupled", "h1"):
        raise BadInputError(f"{rec.path}: the coupled model needs the end mass, which is not recorded")
    return make_model(key, float(rec.end_mass_kg or 0.0), float(rec.load_mass_kg))


def measured_response(rec: Recording, n_harmonics: int = 3) -> tuple[frfmod.FrequencyResponse,
                                                                     list[StepSignal], list[str]]:
    """H(f) from every usable step, the per-step signals for OE, and notes on skipped steps."""
    items, sigs, notes = [], [], []
    fs = rec.sample_rate_hz
    for st in rec.steps:
        if not st.usable:
            notes.append(f"step {st.index} skipped: {st.lost_in_window} samples lost in its window")
            continue
        x, u = rec.step_signals(st)
        t = np.arange(st.start_sample, st.end_sample) / fs
        it = frfmod.step_response(t, x, u, st.crank_frequency_hz, n_harmonics=n_harmonics)
        items.append(it)
        sigs.append(StepSignal(t, u, it[2], np.array((it[2].phasor, *it[2].harmonics))))
    if not items:
        raise BadInputError(f"{rec.path}: no usable step")
    return frfmod.assemble(items), sigs, notes


def _start(frf: frfmod.FrequencyResponse, model: SdofModel) -> FloatArray:
    """theta0: linear LS on 1/H with >= 2 frequencies, else |H|/M with a far resonance (the k_f, b_f
    start values are then arbitrary, held, and reported as not identifiable; S is then the
    quasi-static sensitivity, low by about M w^2 / k_f relative)."""
    if np.unique(np.round(frf.f_hz, 6)).size >= 2:
        th = frfmod.linear_start_sdof(frf, model)
        if np.all(np.isfinite(th)) and np.all(th > 0):
            return th
    w = 2 * np.pi * float(np.max(frf.f_hz))
    k0 = 1e6 * model.M * w**2  # resonance 1000 x f: S is then the quasi-static |H|/M
    return np.array([float(np.mean(np.abs(frf.H))) / model.M, k0, 0.1 * np.sqrt(k0 * model.M)])


def _params(model: Model, theta: FloatArray, cov: FloatArray, ident: tuple[bool, ...],
            reasons: tuple[str, ...]) -> tuple[ParameterEstimate, ...]:
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    return tuple(ParameterEstimate(n, u, float(theta[i]) if ident[i] else None,
                                   float(std[i]) if ident[i] else None, ident[i], reasons[i])
                 for i, (n, u) in enumerate(zip(model.names, model.units, strict=True)))


def _fd_fit(frf: frfmod.FrequencyResponse, model: Model, theta0: FloatArray,
            policy: Policy) -> tuple[frfmod.FrfFit, Identifiability]:
    """Fit the structurally identifiable parameters (all, when the data allow), holding the others at
    theta0; judge identifiability at the estimate.  The covariance is that of the identifiable
    subset with the others held (conditional), so confounded parameters cannot inflate it."""
    _, ok0 = assess(model, theta0, frf, policy)
    fit = frfmod.fit_frf(frf, model, theta0, free=ok0, inflate=bool(ok0.all()))
    scale = np.maximum(np.abs(fit.theta), 0.1 * np.abs(theta0))  # b_c may sit at 0
    rep, ok = assess(model, fit.theta, frf, policy, scale)
    cov = np.zeros_like(fit.cov)
    if ok.any():
        J = frfmod.whitened_jacobian(model, fit.theta, frf, scale=scale)[:, ok]
        birge = fit.chi2 / fit.dof if fit.inflated else 1.0
        cov[np.ix_(ok, ok)] = birge * np.linalg.pinv(J.T @ J) * np.outer(scale[ok], scale[ok])
        # report the correlations of this estimate; the assessment's (with the chain floor and a
        # regulariser, where +-1 marks confounding) stay only for parameters that are not identifiable
        corr = np.array(rep.correlations)
        corr[np.ix_(ok, ok)] = correlations(cov[np.ix_(ok, ok)])
        rep = replace(rep, correlations=tuple(tuple(float(c) for c in row) for row in corr))
    return replace(fit, cov=cov), rep


def _summary_fd(frf: frfmod.FrequencyResponse, fit: frfmod.FrfFit, sigs: list[StepSignal]) -> FitSummary:
    """Per-step model residual RMS in V: sine-fit residual plus the fundamental's misfit."""
    rms = []
    n = []
    for i, s in enumerate(sigs):
        A = (2 * np.pi * frf.f_hz[i]) ** 2 * abs(s.fit_x.phasor)
        rms.append(float(np.sqrt(frf.force_rms_residual_V[i] ** 2 + (abs(fit.residual[i]) * A) ** 2 / 2)))
        n.append(s.t.size)
    mse = float(np.sum(np.square(rms) * n) / np.sum(n))
    return FitSummary(mse, tuple(rms), fit.chi2 / fit.dof if fit.dof else float("nan"), int(np.sum(n)))


def identify_fd(rec: Recording, model_key: str = "sdof",
                policy: Policy = DEFAULT_POLICY) -> IdentificationResult:
    """Frequency-domain estimator (sine fits, 1/H start, weighted LM) with identifiability.

    model_key 'auto': Eq. 9, or Eq. 8 when Eq. 9 misfits (chi2/dof significantly > 1) and the
    coupled model determines k_c and fits (chi2/dof consistent with the noise)."""
    frf, sigs, notes = measured_response(rec)
    sdof = model_for(rec, "sdof")
    assert isinstance(sdof, SdofModel)
    fit, rep = _fd_fit(frf, sdof, _start(frf, sdof), policy)
    model: Model = sdof
    auto = model_key == "auto"
    if model_key in ("coupled", "h1") or (auto and fit.inflated and rec.end_mass_kg):
        cm = model_for(rec, "coupled")
        assert isinstance(cm, CoupledModel)
        th0 = np.r_[fit.theta, 10 * fit.theta[1], 0.1 * fit.theta[2]]
        cfit, crep = _fd_fit(frf, cm, th0, policy)
        c2, s2 = cfit.chi2 / max(cfit.dof, 1), fit.chi2 / max(fit.dof, 1)
        if crep.identifiable[3] and (not auto or (c2 < 0.25 * s2 and not cfit.inflated)):
            if auto:
                notes.append(f"model chosen: coupled (Eq. 8), chi2/dof {c2:.3g} against {s2:.3g} for Eq. 9")
            fit, rep, model = cfit, crep, cm
        elif auto:
            notes.append(f"Eq. 9 misfits (chi2/dof {s2:.3g}) but the coupled model does not determine k_c "
                         "either; unmodelled effects (conditioner filter, channel delay) are likely")
        else:
            model = cm
            notes.append("k_c not identifiable: S, k_f, b_f are given in the stiff-coupling "
                         "limit (Eq. 9, k_c -> inf, b_c -> 0)")
            theta = np.r_[fit.theta, cfit.theta[3:]]
            cov = np.zeros((5, 5))
            cov[:3, :3] = fit.cov
            ident = (*rep.identifiable, False, False)
            reasons = (*rep.reasons[:3], crep.reasons[3] or "k_c not identifiable", crep.reasons[4]
                       or "b_c is meaningless without k_c")
            rep = replace(crep, identifiable=ident, reasons=reasons)
            fit = replace(fit, theta=theta, cov=cov)
    if not all(rep.identifiable[:3]):
        notes.append("parameters that are not identifiable were held at start values; the others' "
                     "uncertainties are conditional on them (S from one frequency is |H|/M, low by "
                     "about M w^2/k_f relative)")
    if fit.inflated:
        notes.append(f"chi2/dof = {fit.chi2 / fit.dof:.3g}: uncertainties inflated by sqrt(chi2/dof)")
    params = _params(model, fit.theta, fit.cov, rep.identifiable, rep.reasons)
    extra = {"m_e_kg": model.m_e, "m_l_kg": model.m_l, "f_hz": frf.f_hz.tolist(), "H_abs": np.abs(frf.H).tolist(),
             "H_phase_rad": np.angle(frf.H).tolist(),
             "H_std": np.sqrt(np.trace(frf.cov, axis1=1, axis2=2) / 2).tolist()}
    return IdentificationResult("fd", model.key, params, _summary_fd(frf, fit, sigs), rep, tuple(notes),
                                extra)


def identify_oe(rec: Recording, model_key: str = "sdof",
                policy: Policy = DEFAULT_POLICY) -> IdentificationResult:
    """Time-domain output error on the raw force samples, started from the FD estimate."""
    frf, sigs, notes = measured_response(rec)
    model = model_for(rec, "coupled" if model_key in ("coupled", "h1") else "sdof")
    fd = identify_fd(rec, model.key, policy)
    ok = np.array(fd.identifiability.identifiable) if fd.identifiability else np.ones(len(model.names), bool)
    sd = model_for(rec, "sdof")
    assert isinstance(sd, SdofModel)
    th0 = frfmod.fit_frf(frf, sd, _start(frf, sd)).theta
    if model.key == "coupled":
        th0 = np.r_[th0, 10 * th0[1], 0.1 * th0[2]]
        if not ok[3]:
            model, ok, th0 = sd, ok[:3], th0[:3]
    fit = fit_oe(sigs, model, th0, free=ok)
    rep = fd.identifiability
    ident = tuple(bool(v) for v in ok)
    reasons = rep.reasons[: len(ident)] if rep else ("",) * len(ident)
    params = list(_params(model, fit.theta, fit.cov, ident, reasons))
    if len(params) < len(fd.parameters):
        params += list(fd.parameters[len(params):])
        notes.append("k_c, b_c not identifiable: OE fit in the stiff-coupling limit (Eq. 9)")
    summary = FitSummary(fit.mse, tuple(float(v) for v in fit.residual_rms_V), float("nan"),
                         int(sum(s.t.size for s in sigs)))
    return IdentificationResult("oe", fd.model, tuple(params), summary, rep, tuple(notes),
                                {"offsets_V": fit.offsets_V.tolist()})


def store_result(path: str | Path, res: IdentificationResult) -> str:
    """Write ``res`` into the recording's /results (replacing an earlier one); returns its path in the file."""
    write_results(path, res.result_name, res.to_dict())
    return f"/results/{res.result_name}"


def identify_recording(rec: Recording, method: str | None = None, model: str | None = None, *,
                       seed: int = 0, protocol: PaperProtocol = DEFAULT_PROTOCOL,
                       policy: Policy = DEFAULT_POLICY) -> IdentificationResult:
    """Identify the transducer from a recording.  Default method: 'fd' (the efficient estimator
    for stepped-sine data, at the Cramér-Rao bound; with a single frequency it reports what is not
    identifiable); default model: 'auto' for fd (Eq. 9, Eq. 8 when the data demand and determine
    it), 'sdof' for oe, 'h2' for the paper's methods."""
    method = method or "fd"
    if method not in METHODS:
        raise BadInputError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
    if model is not None and model not in MODELS:
        raise BadInputError(f"unknown model {model!r}; expected one of {', '.join(MODELS)}")
    if method == "fd":
        return identify_fd(rec, model or "auto", policy)
    if method == "oe":
        return identify_oe(rec, model or "sdof", policy)
    form = {"sdof": "h2", "coupled": "h1"}.get(model or "h2", model or "h2")
    if method == "rls" and form != "h2":
        raise BadInputError("RLS (Eq. 17) is defined for H2 (Eq. 11) only")
    return identify_paper_method(rec, method, form, model_for(rec, form), seed=seed, protocol=protocol,
                                 policy=policy)
