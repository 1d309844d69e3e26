"""Joint weighted least squares of several frequency responses of one transducer with different
top masses (a multi-mass campaign), Eq. 9 per recording r:

    H_r(s) = -S M_r k_f / (M_r s^2 + b_f s + k_f),   M_r = m_e + m_l,r           (Eq. 9, ``models``)

Parameters p = (S [V/N], m_e [kg], k_f [N/m], b_f [N s/m], m_l,1 ... m_l,R [kg]).  The load masses
are weighed, not known exactly: each enters as a parameter with a prior observation
(m_l,r^weighed - m_l,r) / u_r, so their standard uncertainties u_r propagate into S, m_e, k_f, b_f
(u_r = 0 holds m_l,r fixed).  chi^2(p) = sum_r sum_i r_ri^T C_ri^-1 r_ri + sum_r prior_r^2 with
r_ri = (Re, Im)(H_r(f_i; p) - H_ri), C_ri the covariance of the measured H (``response.frf``).

With one load mass Eq. 9 depends on S M, k_f / M and b_f / M only (three numbers for four
parameters: S, m_e confounded).  Each recording fixes its M_r = m_e + m_l,r up to a scale common to
all (twice: the gain S M_r and the natural frequency k_f / M_r), so two or more distinct load masses,
whose differences are known, fix that scale and separate S from m_e.  The same structure means that
two recordings fit any two stated masses (a mass error goes into m_e); from three on they check
each other.

Covariance: Gauss-Markov (J^T J)^-1 of the whitened Jacobian at the estimate (Cramér-Rao bound for
Gaussian H), scaled by chi^2/dof when that is significantly above 1 (Birge ratio), as ``response.frf.fit_frf``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from station.ident.models import SdofModel
from station.ident.response.frf import FrequencyResponse, fit_frf, linear_start_sdof, whiteners

FloatArray = NDArray[np.float64]
NAMES = ("S", "m_e", "k_f", "b_f")
UNITS = ("V/N", "kg", "N/m", "N*s/m")


@dataclass(frozen=True)
class MassPrior:
    """A weighed load mass m_l (top mass + adaption) in kg and its standard uncertainty in kg."""

    value: float
    std: float


@dataclass(frozen=True)
class JointFit:
    """Result of ``fit_joint``.

    theta: (S, m_e, k_f, b_f) in (V/N, kg, N/m, N s/m), shape (4,); cov: their covariance (4, 4),
    the load masses marginalised; load_mass, load_mass_std: fitted m_l,r and standard uncertainty
    (kg), shape (R,); chi2, dof: of data and priors; chi2_by_recording: each recording's data part;
    inflated: covariance scaled by chi2/dof; fisher_rel: Fisher information of (S, m_e, k_f, b_f)
    with the load masses eliminated (Schur complement), in relative units (S, k_f, b_f relative
    to their values, m_e relative to the mean M), shape (4, 4).
    """

    theta: FloatArray
    cov: FloatArray
    load_mass: FloatArray
    load_mass_std: FloatArray
    chi2: float
    dof: int
    chi2_by_recording: FloatArray
    inflated: bool
    fisher_rel: FloatArray
    scale: FloatArray

    @property
    def chi2_per_dof(self) -> float:
        return self.chi2 / self.dof if self.dof else float("nan")


def _response_and_jacobian(p: FloatArray, m_l: float, f_hz: FloatArray) -> tuple[NDArray[np.complex128],
                                                                                  NDArray[np.complex128]]:
    """H(f) of Eq. 9 and dH/d(S, m_e, k_f, b_f, m_l), shape (n_f,) and (n_f, 5), analytic:
    dH/dS = H/S, dH/dM = -S k_f (b_f s + k_f)/D^2, dH/dk_f = H (1/k_f - 1/D), dH/db_f = -H s/D."""
    S, m_e, k, b = p[:4]
    M = m_e + m_l
    s = 2j * np.pi * f_hz
    D = M * s**2 + b * s + k
    H = -S * M * k / D
    dM = -S * k * (b * s + k) / D**2
    return H, np.column_stack([-M * k / D, dM, H * (1.0 / k - 1.0 / D), -H * s / D, dM])


def _system(frfs: list[FrequencyResponse], priors: list[MassPrior], cov_of: list[FloatArray] | None = None,
            ) -> tuple[Callable[[FloatArray], tuple[FloatArray, FloatArray]], list[bool]]:
    """Whitened residual and Jacobian functions of the scaled parameters x = p / scale."""
    W = [whiteners(f.cov if cov_of is None else cov_of[i]) for i, f in enumerate(frfs)]
    R = len(frfs)
    held = [pr.std <= 0 for pr in priors]

    def resid_jac(p: FloatArray) -> tuple[FloatArray, FloatArray]:
        rows, jrows = [], []
        for r, frf in enumerate(frfs):
            H, J5 = _response_and_jacobian(p, p[4 + r], frf.f_hz)
            d = H - frf.H
            rows.append(np.einsum("fij,fj->fi", W[r], np.column_stack([d.real, d.imag])).ravel())
            J = np.zeros((frf.f_hz.size, 4 + R), complex)
            J[:, :4] = J5[:, :4]
            J[:, 4 + r] = J5[:, 4]
            Jr = np.stack([J.real, J.imag], axis=1)
            jrows.append(np.einsum("fij,fjk->fik", W[r], Jr).reshape(-1, 4 + R))
        for r, pr in enumerate(priors):
            if held[r]:
                continue
            row = np.zeros(4 + R)
            rows.append(np.array([(p[4 + r] - pr.value) / pr.std]))
            row[4 + r] = 1.0 / pr.std
            jrows.append(row[None, :])
        return np.concatenate(rows), np.vstack(jrows)

    return resid_jac, held


def start_values(frfs: list[FrequencyResponse], priors: list[MassPrior], m_e0: float) -> FloatArray:
    """(S, m_e, k_f, b_f) from one fit per recording with m_e = 0: its S'_r m_l,r = S (m_e + m_l,r) and
    m_l,r / k'_r = (m_e + m_l,r) / k_f are linear in m_l,r; with fewer than two distinct masses
    m_e = m_e0 (the stated or assumed end mass)."""
    g, a, bk, ml = [], [], [], []
    for frf, pr in zip(frfs, priors, strict=True):
        model = SdofModel(0.0, pr.value)
        th = fit_frf(frf, model, linear_start_sdof(frf, model), inflate=False).theta
        g.append(th[0] * pr.value)
        a.append(pr.value / th[1])
        bk.append(th[2] / th[1])
        ml.append(pr.value)
    g_, a_, m = np.array(g), np.array(a), np.array(ml)
    if np.ptp(m) > 1e-9 * np.max(m):
        slope, icpt = np.polyfit(m, g_, 1)
        S, m_e = slope, icpt / slope
    else:
        m_e = m_e0
        S = float(np.mean(g_ / (m + m_e)))
    k = float(np.mean((m + m_e) / a_))
    return np.array([S, m_e, k, float(np.mean(bk)) * k])


def fit_joint(frfs: list[FrequencyResponse], priors: list[MassPrior], theta0: FloatArray,
              *, free_m_e: bool = True, m_e_prior: MassPrior | None = None) -> JointFit:
    """Weighted LM of (S, m_e, k_f, b_f) and the load masses over all recordings (module docstring).

    free_m_e False holds m_e at theta0[1] (or, with m_e_prior, treats it as one more prior
    observation): the conditional fit used when the masses cannot separate S from m_e."""
    R = len(frfs)
    resid_jac, held = _system(frfs, priors)
    M_mean = float(np.mean([pr.value for pr in priors])) + abs(float(theta0[1]))
    scale = np.r_[abs(theta0[0]), M_mean, abs(theta0[2]), abs(theta0[3]), [max(pr.value, 1e-3) for pr in priors]]
    p0 = np.r_[theta0, [pr.value for pr in priors]]
    free = np.ones(4 + R, bool)
    free[4:] = ~np.array(held)
    use_prior = m_e_prior is not None and m_e_prior.std > 0
    if not free_m_e and not use_prior:
        free[1] = False

    def full(x: FloatArray) -> FloatArray:
        p: FloatArray = p0.copy()
        p[free] = p0[free] + x * scale[free]
        return p

    def rj(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        r, J = resid_jac(full(x))
        if use_prior:
            assert m_e_prior is not None
            row = np.zeros(4 + R)
            row[1] = 1.0 / m_e_prior.std
            r = np.r_[r, (full(x)[1] - m_e_prior.value) / m_e_prior.std]
            J = np.vstack([J, row])
        return r, (J * scale[None, :])[:, free]

    sol = least_squares(lambda x: rj(x)[0], np.zeros(int(free.sum())), jac=lambda x: rj(x)[1], method="lm",
                        xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=500)
    p = full(sol.x)
    r, Jw = rj(sol.x)
    chi2 = float(r @ r)
    dof = max(r.size - int(free.sum()), 0)
    cov_x = np.linalg.pinv(Jw.T @ Jw)
    inflated = bool(dof > 0 and chi2 / dof > 1 + 3 * np.sqrt(2.0 / dof))
    if inflated:
        cov_x *= chi2 / dof
    cov_p = np.zeros((4 + R, 4 + R))
    idx = np.nonzero(free)[0]
    cov_p[np.ix_(idx, idx)] = cov_x * np.outer(scale[idx], scale[idx])
    by_rec = []
    off = 0
    for frf in frfs:
        n = 2 * frf.f_hz.size
        by_rec.append(float(r[off:off + n] @ r[off:off + n]))
        off += n
    return JointFit(p[:4], cov_p[:4, :4], p[4:], np.sqrt(np.clip(np.diag(cov_p)[4:], 0, None)), chi2, dof,
                    np.array(by_rec), inflated, fisher_relative(frfs, priors, p, scale, None), scale[:4])


def fisher_relative(frfs: list[FrequencyResponse], priors: list[MassPrior], p: FloatArray,
                    scale: FloatArray, cov_of: list[FloatArray] | None) -> FloatArray:
    """Fisher information of (S, m_e, k_f, b_f) per unit of ``scale`` with the load masses eliminated
    (Schur complement over their block, priors included), shape (4, 4).  cov_of: covariances of H
    to use instead of the measured ones (e.g. with a measurement-chain floor added)."""
    resid_jac, held = _system(frfs, priors, cov_of)
    _, J = resid_jac(p)
    J = J * scale[None, :]
    keep = np.r_[np.ones(4, bool), ~np.array(held)]
    F = J[:, keep].T @ J[:, keep]
    A, B, C = F[:4, :4], F[:4, 4:], F[4:, 4:]
    fisher: FloatArray = A - B @ np.linalg.pinv(C) @ B.T if C.size else A
    return fisher


def data_sensitivity(frfs: list[FrequencyResponse], priors: list[MassPrior], p: FloatArray,
                     scale: FloatArray, free4: NDArray[np.bool_],
                     m_e_std: float | None = None) -> Callable[[list[NDArray[np.complex128]]], FloatArray]:
    """First-order response of (S, m_e, k_f, b_f) to a systematic change dH_r of the measured H of
    every recording (GUM sensitivity coefficients, as ``fd.budget``): d theta = -(J^T J)^-1 J^T [W dH; 0]
    with J the whitened Jacobian of ``fit_joint``'s problem at p (load-mass priors, and an end-mass
    prior of std m_e_std when m_e is free but not in free4's sense of separated).  free4: which of
    the four are estimated.  Returns a function of the list of dH_r (each (n_f,) complex)."""
    R = len(frfs)
    resid_jac, held = _system(frfs, priors)
    _, J = resid_jac(p)
    free = np.r_[free4, ~np.array(held)]
    if m_e_std is not None and m_e_std > 0:
        row = np.zeros(4 + R)
        row[1] = 1.0 / m_e_std
        J = np.vstack([J, row])
        free[1] = True
    Js = J[:, free] * scale[free][None, :]
    pinv = np.linalg.pinv(Js)
    W = [whiteners(f.cov) for f in frfs]
    n_data = sum(2 * f.f_hz.size for f in frfs)

    def apply(dH: list[NDArray[np.complex128]]) -> FloatArray:
        v = np.zeros(Js.shape[0])
        v[:n_data] = np.concatenate([np.einsum("fij,fj->fi", W[r], np.column_stack([d.real, d.imag])).ravel()
                                     for r, d in enumerate(dH)])
        dx = np.zeros(4 + R)
        dx[free] = -(pinv @ v) * scale[free]
        out = dx[:4].copy()
        if not free4[1]:
            out[1] = 0.0
        return out

    return apply
