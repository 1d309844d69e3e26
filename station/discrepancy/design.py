"""Planned data: the measured steps plus candidate steps not yet run, with the coefficients a given
model predicts (no noise) and the weights the noise would give them.  Used to ask, before anything
moves, how well a planned run would separate two models or determine a parameter.

For a planned step (crank frequency f Hz, radius r m, record time T s, N = T fs samples) the
decomposition basis of ``decompose`` is (nearly) orthogonal over whole periods: each cos/sin pair
has Gram N/2 I, the polynomial [1, u, u^2] (u = tau/h in [-1, 1]) has Gram N [[1, 0, 1/3], [0, 1/3, 0],
[1/3, 0, 1/5]].  So R = chol of that Gram (n_f x n_f), and the noise sigma of the planned step is the
median force (displacement) noise of the measured steps; the displacement fundamental covariance is
2 sigma_d^2 / N I (m^2).  The measured steps keep their own R, sigma and coefficient covariance.

``expected_chi2(design, fit)``: chi^2 of model ``fit`` refitted (all its parameters free) to the
coefficients of the design, i.e. the expected increase of chi^2 of that model over the true one if the
design's model were true (the noise adds the same amount to both; Delta chi^2 is its non-centrality).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from station.discrepancy.data import RigData
from station.discrepancy.decompose import K_MAX
from station.discrepancy.fit import ModelFit, Problem, fit_model
from station.discrepancy.model import predict

FloatArray = NDArray[np.float64]
_POLY_GRAM = np.array([[1.0, 0.0, 1 / 3], [0.0, 1 / 3, 0.0], [1 / 3, 0.0, 1 / 5]])


def planned_data(data: RigData, steps: Sequence[tuple[float, float]], record_s: float,
                 gap_s: float) -> RigData:
    """``data`` with the planned steps (crank frequency Hz, radius m) appended, each recorded for
    ``record_s`` s, ``gap_s`` s apart after the last measured step; coefficients zero (see
    ``with_model``)."""
    m = len(steps)
    if m == 0:
        return data
    fs = data.sample_rate_hz
    N = max(round(record_s * fs), 16)
    nf, nd = data.cf.shape[1], data.cd.shape[1]
    K = K_MAX
    Rf, Rd = np.zeros((m, nf, nf)), np.zeros((m, nd, nd))
    kmask = np.zeros((m, K), dtype=bool)
    f = np.array([s[0] for s in steps], dtype=float)
    for i, fi in enumerate(f):
        k_top = int(max(1, min(K, math.floor(0.45 * fs / fi))))
        kmask[i, :k_top] = True
        harm = np.zeros(nf)
        harm[: 2 * k_top] = math.sqrt(N / 2)
        harm[2 * K + 3 :] = math.sqrt(N / 2)  # mains lines in their own slots
        Rf[i] = np.diag(harm)
        Rf[i][2 * K : 2 * K + 3, 2 * K : 2 * K + 3] = math.sqrt(N) * np.linalg.cholesky(_POLY_GRAM).T
        Rd[i] = np.diag(np.r_[np.full(2 * (k_top - 1), math.sqrt(N / 2)), np.zeros(nd - 2 * (k_top - 1))])
    sig_f, sig_d = float(np.median(data.sigma_f)), float(np.median(data.sigma_d))
    t_end = float(np.max(data.t_mid_s + data.half_s))
    t_mid = t_end + gap_s * np.arange(1, m + 1) + record_s / 2
    x1 = np.array([complex(s[1], 0.0) for s in steps])
    cat = np.concatenate
    return replace(
        data, f_hz=cat([data.f_hz, f]), x1=cat([data.x1, x1]),
        x1_cov=cat([data.x1_cov, np.repeat((2 * sig_d**2 / N * np.eye(2))[None], m, axis=0)]),
        t_mid_s=cat([data.t_mid_s, t_mid]), half_s=cat([data.half_s, np.full(m, record_s / 2)]),
        kmask=cat([data.kmask, kmask]), Rf=cat([data.Rf, Rf]), cf=cat([data.cf, np.zeros((m, nf))]),
        sigma_f=cat([data.sigma_f, np.full(m, sig_f)]),
        ssr_f=cat([data.ssr_f, np.full(m, sig_f**2 * max(N - nf, 1))]),
        n_samples=cat([data.n_samples, np.full(m, float(N))]), Rd=cat([data.Rd, Rd]),
        cd=cat([data.cd, np.zeros((m, nd))]), sigma_d=cat([data.sigma_d, np.full(m, sig_d)]),
        merge=cat([data.merge, np.zeros((m, data.n_mains), dtype=np.int64)]),
        Rx=cat([data.Rx, np.zeros((m, *data.Rx.shape[1:]))]), bx=cat([data.bx, np.zeros((m, data.bx.shape[1]))]))


def with_model(design: RigData, truth: ModelFit) -> RigData:
    """The design with the coefficients the model ``truth`` predicts (noise-free), all steps."""
    m_f, m_d, _ = predict(design, truth.values, truth.effects)
    return replace(design, cf=m_f * np.any(design.Rf != 0, axis=1), cd=m_d * np.any(design.Rd != 0, axis=1))


def expected_chi2(design: RigData, fit: ModelFit, max_nfev: int = 200) -> float:
    """chi^2 of ``fit``'s model refitted to the design's coefficients (module docstring)."""
    try:
        return float(fit_model(design, fit.effects, fit.values, max_nfev=max_nfev).chi2)
    except (ValueError, np.linalg.LinAlgError, FloatingPointError):
        return math.nan


def linearised(design: RigData, fit: ModelFit, eps: float = 1e-4
               ) -> tuple[FloatArray, FloatArray, NDArray[np.int64], Problem]:
    """(r, J, step of each row, problem): the whitened residual of ``fit``'s model at its fitted
    values against the design's coefficients and its Jacobian in the fit's internal variables
    (forward differences), for choosing steps by linear algebra on row subsets."""
    prob = Problem(design, fit.effects, fit.values)
    u = np.zeros(len(prob.params))
    r0 = prob.residual(u)
    J = prob.jacobian(u, step=eps)
    rows = np.concatenate([np.nonzero(prob.valid_f)[0], np.nonzero(prob.valid_d)[0]])
    return r0, J, rows, prob


def projected_chi2(r: FloatArray, J: FloatArray, keep: NDArray[np.bool_]) -> float:
    """||(I - P_J) r||^2 over the rows ``keep``: chi^2 left after a first-order refit."""
    rs, Js = r[keep], J[keep]
    coef, *_ = np.linalg.lstsq(Js, rs, rcond=None)
    e = rs - Js @ coef
    return float(e @ e)
