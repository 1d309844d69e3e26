"""Core of the frequency-domain estimator: start values, the weighted fit of the structurally
identifiable parameters with the estimate's covariance, and the fit summary (``response.frf`` has
H(f) and the LM; ``fd.identify`` the whole estimator with checks and budget)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from station.ident.identifiability import Policy, assess, correlations
from station.ident.models import Model, SdofModel
from station.ident.response import frf as frfmod
from station.ident.response.checked import StepSignal
from station.ident.result import FitSummary, Identifiability

FloatArray = NDArray[np.float64]


def start_values(frf: frfmod.FrequencyResponse, model: SdofModel, sign: float = 1.0) -> FloatArray:
    """theta0: linear LS on 1/H with >= 2 frequencies, else |H|/M with a far resonance (the k_f, b_f
    start values are then arbitrary and held; |H|/M is then HIGH against S by about M w^2 / k_f
    relative).  S may be negative (inverted polarity): sign is that of S at the lowest frequency."""
    if np.unique(np.round(frf.f_hz, 6)).size >= 2:
        th = frfmod.linear_start_sdof(frf, model)
        if np.all(np.isfinite(th)) and np.all(th[1:] > 0) and th[0] * sign > 0:
            return th
    w = 2 * np.pi * float(np.max(frf.f_hz))
    k0 = 1e6 * model.M * w**2  # resonance 1000 x f: S is then the quasi-static |H|/M
    return np.array([sign * float(np.mean(np.abs(frf.H))) / model.M, k0, 0.1 * np.sqrt(k0 * model.M)])


def fd_fit(frf: frfmod.FrequencyResponse, model: Model, theta0: FloatArray,
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


def summary_fd(frf: frfmod.FrequencyResponse, fit: frfmod.FrfFit, sigs: list[StepSignal]) -> FitSummary:
    """Per-step model residual RMS in V: sine-fit residual plus the fundamental's misfit."""
    rms = []
    n = []
    for i, s in enumerate(sigs):
        A = (2 * np.pi * frf.f_hz[i]) ** 2 * abs(s.fit_x.phasor)
        rms.append(float(np.sqrt(frf.force_rms_residual_V[i] ** 2 + (abs(fit.residual[i]) * A) ** 2 / 2)))
        n.append(s.t.size)
    mse = float(np.sum(np.square(rms) * n) / np.sum(n))
    return FitSummary(mse, tuple(rms), fit.chi2 / fit.dof if fit.dof else float("nan"), int(np.sum(n)))
