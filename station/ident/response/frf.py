"""Frequency-domain identification: H(f) per step from sine fits, a linear LS start on 1/H and
a weighted Levenberg-Marquardt refinement of the physical parameters over all steps.

Per step i: X_i (displacement phasor, m) and U_i (force phasor, V) at the same frequency and time
origin; acceleration phasor A_i = -(2 pi f_i)^2 X_i; H_i = U_i / A_i in V/(m/s^2), covariance by
linear propagation (channels independent):  dH = dU / A - H dA / A.

Weighted LS: chi^2(theta) = sum_i r_i^T C_i^-1 r_i, r_i = (Re, Im)(H_model(f_i; theta) - H_i).
Covariance of theta: (J_w^T J_w)^-1 with J_w the whitened Jacobian (Gauss-Markov; equals the
Cramér-Rao bound of ``crb.py`` when C_i is the true covariance).  If chi^2/dof is significantly
above 1 the covariance is inflated by chi^2/dof (Birge ratio) and a note says so.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from station.ident.models import Model, SdofModel
from station.ident.response.sinefit import SineFit, estimate_frequency, fit_channels, with_quantisation
from station.kept import Kept, content_key

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]
# one step's measurement: H, cov (2, 2) of (Re H, Im H), the displacement's and the force's sine fits
StepItem = tuple[complex, FloatArray, SineFit, SineFit]
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrequencyResponse:
    """Measured H at the step frequencies: f_hz (n,), H (n,) complex in V/(m/s^2), cov (n, 2, 2)
    of (Re H, Im H); force_rms_residual_V (n,) per step; force_offset_V (n,)."""

    f_hz: FloatArray
    H: ComplexArray
    cov: FloatArray
    force_rms_residual_V: FloatArray
    force_offset_V: FloatArray


def ratio_cov(U: complex, Cu: FloatArray, A: complex, Ca: FloatArray) -> tuple[complex, FloatArray]:
    """H = U/A of two phasors (covariances Cu, Ca (2, 2) of their real and imaginary parts) and
    cov(Re H, Im H) (2, 2) by the delta method (U, A independent)."""
    def cmul(z: complex) -> FloatArray:  # real 2x2 matrix of multiplication by z
        return np.array([[z.real, -z.imag], [z.imag, z.real]])
    H = U / A
    Ju, Ja = cmul(1.0 / A), cmul(-H / A)
    return H, Ju @ Cu @ Ju.T + Ja @ Ca @ Ja.T


STEP_CACHE_SIZE = 256  # steps whose H is kept (a few kB each)


def _fresh(item: StepItem) -> StepItem:
    """A copy of a step's item whose arrays the caller may change without changing the kept one."""
    H, C, fx, fu = item
    return (H, C.copy(), replace(fx, phasor_cov=fx.phasor_cov.copy()), replace(fu, phasor_cov=fu.phasor_cov.copy()))


_steps: Kept[StepItem] = Kept(STEP_CACHE_SIZE, _fresh)


def step_response(t: FloatArray, x_m: FloatArray, u_V: FloatArray, f_nominal_hz: float,
                  *, n_harmonics: int = 3, fit_frequency: bool = True) -> StepItem:
    """H at one step: 4-parameter fit of the displacement (frequency), 3-parameter fit of the force
    at that frequency, both with harmonics up to n_harmonics as nuisance; a channel's quantisation
    error that its noise does not dither is in its phasor's covariance (``sinefit.quantisation_cov``).
    Returns (H, cov, fx, fu).

    A function of its arguments only: the last ``STEP_CACHE_SIZE`` steps' items are kept by the
    content of their samples and settings (``kept``), so the same data is not fitted twice in a process
    (``step_cache_clear()`` drops them)."""
    key = content_key(t, x_m, u_V, settings=(float(f_nominal_hz), int(n_harmonics), bool(fit_frequency)))
    return _steps.get(key, lambda: _step_response(t, x_m, u_V, f_nominal_hz, n_harmonics, fit_frequency))


def step_cache_clear() -> None:
    """Drop the kept step items (``step_response``) and force frequencies (``redundancy.clock_check``)."""
    from station.ident.response.redundancy import clock_cache_clear

    _steps.clear()
    clock_cache_clear()


def _step_response(t: FloatArray, x_m: FloatArray, u_V: FloatArray, f_nominal_hz: float, n_harmonics: int,
                   fit_frequency: bool) -> StepItem:
    """``step_response`` computed."""
    if fit_frequency:
        f, f_std, tc = estimate_frequency(t, x_m, f_nominal_hz, n_harmonics=n_harmonics)
    else:
        f, f_std, tc = f_nominal_hz, 0.0, float(np.mean(t))
    fit_x, fit_u = fit_channels(t, np.column_stack([x_m, u_V]), f, t_center_s=tc, n_harmonics=n_harmonics)
    fit_x = replace(with_quantisation(t, x_m, fit_x, n_harmonics), frequency_std_hz=f_std)
    fit_u = with_quantisation(t, u_V, fit_u, n_harmonics)
    w2 = (2 * np.pi * fit_x.frequency_hz) ** 2
    H, C = ratio_cov(fit_u.phasor, fit_u.phasor_cov, -w2 * fit_x.phasor, w2**2 * fit_x.phasor_cov)
    return H, C, fit_x, fit_u


def assemble(items: list[StepItem]) -> FrequencyResponse:
    """Stack step results into a FrequencyResponse (sorted as given)."""
    return FrequencyResponse(
        np.array([it[2].frequency_hz for it in items]), np.array([it[0] for it in items]),
        np.array([it[1] for it in items]), np.array([it[3].residual_rms for it in items]),
        np.array([it[3].offset for it in items]))


def linear_start_sdof(frf: FrequencyResponse, model: SdofModel) -> FloatArray:
    """Linear LS on 1/H = alpha w^2 - gamma - j w beta (Eq. 9 inverted) with alpha = 1/(S k_f),
    beta = b_f/(S M k_f), gamma = 1/(S M).  Needs >= 2 distinct frequencies for alpha vs gamma.
    Returns theta0 = (S, k_f, b_f)."""
    w = 2 * np.pi * frf.f_hz
    G = 1.0 / frf.H
    sd = np.sqrt(np.maximum(np.trace(frf.cov, axis1=1, axis2=2) / 2, 1e-300)) / np.abs(frf.H) ** 2
    Are = np.column_stack([w**2, -np.ones_like(w)]) / sd[:, None]
    alpha, gamma = np.linalg.lstsq(Are, G.real / sd, rcond=None)[0]
    beta = float(np.sum(-w * G.imag / sd**2) / np.sum(w**2 / sd**2))
    S = 1.0 / (gamma * model.M)
    k = gamma * model.M / alpha
    return np.array([S, k, beta * k / gamma])


def misfit_threshold(dof: int) -> float:
    """chi^2/dof beyond which a weighted fit of H(f) misfits (``model_misfit``, Birge inflation):
    1 + 3 sqrt(2/dof), three standard deviations of chi^2(dof)/dof above its mean."""
    return 1.0 + 3.0 * float(np.sqrt(2.0 / dof))


def misfit_false_alarm_rate(dof: int) -> float:
    """Stated false-alarm rate of the misfit test on a fit whose H(f) uncertainties are right: the
    chi^2(dof) tail beyond dof * ``misfit_threshold(dof)`` (1.1 % at dof 7, 0.8 % at dof 17)."""
    from scipy.special import chdtrc  # scipy.stats.chi2.sf without importing scipy.stats

    return float(chdtrc(dof, dof * misfit_threshold(dof)))


@dataclass(frozen=True)
class FrfFit:
    """Weighted LM result: theta (n,), cov (n, n), chi2, dof, whitened Jacobian (2m, n) in
    parameter-relative units (d r / d ln theta), residual H_model - H (m,) complex; history: the
    weighted chi^2 at the start and at each Levenberg-Marquardt iteration (each Jacobian evaluation),
    ending with the final chi^2."""

    theta: FloatArray
    cov: FloatArray
    chi2: float
    dof: int
    jac_rel: FloatArray
    residual: ComplexArray
    inflated: bool
    history: tuple[float, ...] = ()


def whiteners(cov: FloatArray) -> FloatArray:
    """Whiteners of the per-frequency covariances cov (n, 2, 2) of (Re H, Im H): W_i with
    W_i C_i W_i^T = I (inverse Cholesky), shape (n, 2, 2); every weighted fit of H(f) uses them."""
    out: FloatArray = np.linalg.inv(np.linalg.cholesky(np.asarray(cov, float).reshape(-1, 2, 2)))
    return out


def whitened_jacobian(model: Model, theta: FloatArray, frf: FrequencyResponse,
                      cov: FloatArray | None = None, scale: FloatArray | None = None,
                      W: FloatArray | None = None) -> FloatArray:
    """d(whitened residual)/d(theta/scale), shape (2 n_f, n_theta); scale defaults to theta
    (then d/d(ln theta)).  A parameter near 0 needs a typical value as scale, or its column
    vanishes and a covariance computed from it becomes conditional on it.  W: the whiteners of
    cov (or of frf.cov), when the caller has them already (a fit evaluates this at every iteration)."""
    if W is None:
        W = whiteners(frf.cov if cov is None else cov)
    Jc = model.jacobian(theta, frf.f_hz) * (theta if scale is None else scale)[None, :]
    Jr = np.stack([Jc.real, Jc.imag], axis=1)  # (n_f, 2, n_theta)
    J: FloatArray = np.einsum("fij,fjk->fik", W, Jr).reshape(-1, theta.size)
    return J


LOG_RANGE = float(np.log(1e15))  # a parameter moves at most 1e15-fold from its start in a fit


def fit_frf(frf: FrequencyResponse, model: Model, theta0: FloatArray,
            free: NDArray[np.bool_] | None = None, inflate: bool = True) -> FrfFit:
    """Weighted nonlinear LS (Levenberg-Marquardt) of the free parameters, others held at theta0.

    Parameters are optimised as p = ln(theta/theta0) (all physical parameters are positive except
    that S may be negative for an inverted channel; its sign is kept), within +-``LOG_RANGE``: a
    parameter the data leave free along a limit at infinity (b_c of a rigid coupling) would otherwise
    walk to 1e293 and overflow its covariance; at 1e15 times its start it is in that limit already."""
    theta0 = np.asarray(theta0, float)
    free = np.ones(theta0.size, bool) if free is None else np.asarray(free, bool)
    W = whiteners(frf.cov)

    def theta_of(p: FloatArray) -> FloatArray:
        th = theta0.copy()
        th[free] = theta0[free] * np.exp(np.clip(p, -LOG_RANGE, LOG_RANGE))
        return th

    history: list[float] = []
    last: list[float] = []

    def resid(p: FloatArray) -> FloatArray:
        # a trial step of the LM may reach beyond exp's range (a parameter near 0, e.g. b_c): its residuals
        # are then not finite and the LM rejects the step and shortens the next, as it should
        with np.errstate(over="ignore", invalid="ignore"):
            d = model.response(theta_of(p), frf.f_hz) - frf.H
        r: FloatArray = np.einsum("fij,fj->fi", W, np.column_stack([d.real, d.imag])).ravel()
        last[:] = [float(r @ r)]
        return r

    def jac(p: FloatArray) -> FloatArray:
        history.extend(last)  # the cost at the point the iteration starts from
        J = whitened_jacobian(model, theta_of(p), frf, W=W)[:, free]
        J[:, np.abs(p) >= LOG_RANGE] = 0.0  # held at the end of its range: the residual no longer moves
        return J

    from scipy.optimize import least_squares  # here: a report or a certificate reads H(f) without fitting it

    n_res = 2 * frf.f_hz.size
    method = "lm" if n_res >= int(free.sum()) else "trf"
    sol = least_squares(resid, np.zeros(int(free.sum())), jac=jac, method=method,
                        xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=2000)
    theta = theta_of(sol.x)
    Jf = jac(sol.x)
    chi2 = float(sol.fun @ sol.fun)
    dof = max(n_res - int(free.sum()), 0)
    cov_rel = np.linalg.pinv(Jf.T @ Jf)
    inflated = bool(inflate and dof > 0 and chi2 / dof > misfit_threshold(dof))
    if inflated:
        cov_rel *= chi2 / dof
        log.info("chi2/dof = %.3g: covariance inflated (model error or underestimated noise)", chi2 / dof)
    cov = np.zeros((theta.size, theta.size))
    idx = np.nonzero(free)[0]
    cov[np.ix_(idx, idx)] = cov_rel * np.outer(theta[idx], theta[idx])
    return FrfFit(theta, cov, chi2, dof, whitened_jacobian(model, theta, frf, W=W),
                  model.response(theta, frf.f_hz) - frf.H, inflated, (*history[:-1], chi2))
