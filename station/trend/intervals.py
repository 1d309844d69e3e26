"""Calibration intervals from a history, as recommendations for a person to decide on (ISO/IEC 17025
§7.8.4.3: no interval is put on a certificate unless the customer asks).

- ``a3``: NCSLI RP-1 method A3, the interval test, from in-tolerance counts at one assigned interval.
- ``s2``: NCSLI RP-1 method S2, the binomial method, from observed reliabilities at several intervals,
  with the exponential and Weibull reliability models fitted by maximum likelihood.
- ``variables``: the variables method (Castrup; NASA-HDBK-8739.19-5 Annex 5 / chapter 7), from as-found
  deviations against the time since calibration: a polynomial drift model through the origin fitted
  by least squares with its covariance; the interval is where the prediction's confidence bound
  reaches a tolerance limit (reliability target) or where its uncertainty reaches a target.
Times are in days unless the caller uses another unit consistently.

``scipy.optimize`` and ``scipy.stats`` (the binomial and beta functions of A3) are imported where a
method needs them: the daemon computes a history's intervals in its own process, and most histories
need neither (``station.trend.tails`` gives the normal and t functions).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from station.trend.tails import norm_cdf, norm_sf, t_ppf


@dataclass(frozen=True)
class A3Result:
    """Method A3: the recommended interval, the computed one, the confidence with which the current
    interval is rejected, the observed reliability and its confidence range."""

    interval: float
    calculated: float
    rejection_confidence: float
    observed_reliability: float
    reliability_range: tuple[float, float]
    in_tolerance: int
    n: int


def a3(in_tolerance: int, n: int, interval: float, *, target: float = 0.95, max_change: float = 2.0,
       confidence: float = 0.5, min_change: float = 5.0, shortest: float = 14.0,
       longest: float = 1826.0) -> A3Result:
    """NCSLI RP-1 method A3 for ``in_tolerance`` of ``n`` calibrations found in tolerance at the
    assigned ``interval``, against the reliability ``target``.

    The current interval is rejected with confidence Q from the binomial distribution of the
    in-tolerance count at the target reliability; the new interval is the current one scaled by
    10^((R0 - Rt)/(1 - Q)) above target or 10^((R0 - Rt)·Q) below it, bounded by ``max_change`` either
    way, taken when Q exceeds ``confidence`` and the change is at least ``min_change``, then clipped to
    [shortest, longest]."""
    if n < 1 or not 0 <= in_tolerance <= n:
        raise ValueError(f"method A3 needs 0 <= in-tolerance <= n and n >= 1 (got {in_tolerance} of {n})")
    if not 0 < target < 1 or not interval > 0 or not max_change >= 1:
        raise ValueError("method A3 needs 0 < target < 1, an interval > 0 and a maximum change >= 1")
    from scipy import stats  # here: a history without calibrations at the assigned interval needs none of it

    r0 = in_tolerance / n
    if in_tolerance in (0, n):
        q = 1 - stats.binom.pmf(in_tolerance, n, target)
    elif r0 > target:
        q = stats.binom.cdf(in_tolerance, n, target) - 1
    else:
        q = 1 - 2 * stats.binom.cdf(in_tolerance, n, target)
    if r0 > target:
        factor = max_change if q >= 1 else min(10 ** ((r0 - target) / (1 - q)), max_change)
    else:
        factor = max(10 ** ((r0 - target) * q), 1 / max_change)
    calculated = factor * interval
    # the true reliability's range at the stated confidence (Clopper-Pearson style beta bounds)
    if in_tolerance == 0:
        lo, hi = 0.0, 1 - (1 - confidence) ** (1 / n)
    elif in_tolerance == n:
        lo, hi = (1 - confidence) ** (1 / n), 1.0
    else:
        lo = 1 - stats.beta.ppf((1 + confidence) / 2, n - in_tolerance + 1, in_tolerance)
        hi = 1 - stats.beta.ppf((1 - confidence) / 2, n - in_tolerance, in_tolerance + 1)
    new = interval
    if q > confidence and abs(calculated - interval) >= min_change:
        new = min(max(calculated, shortest), longest)
    return A3Result(float(new), float(calculated), float(max(q, 0.0)), r0, (float(lo), float(hi)),
                    in_tolerance, n)


@dataclass(frozen=True)
class S2Model:
    """One reliability model fitted to the binomial data: its parameters, the interval where it
    reaches the target, and its log-likelihood."""

    name: str
    parameters: tuple[float, ...]
    interval: float
    log_likelihood: float


def _loglik(r: np.ndarray, ni: np.ndarray, ri: np.ndarray) -> float:
    r = np.clip(r, 1e-12, 1 - 1e-12)
    return float(np.sum(ni * (ri * np.log(r) + (1 - ri) * np.log(1 - r))))


def s2(times: Sequence[float], reliabilities: Sequence[float], counts: Sequence[float], *,
       target: float) -> list[S2Model]:
    """NCSLI RP-1 method S2 with the exponential R = exp(-λt) and Weibull R = exp(-(λt)^β) models,
    fitted by maximum likelihood to observed reliabilities ``reliabilities`` of ``counts``
    calibrations at ``times``; the models sorted by log-likelihood, best first."""
    t, ri, ni = (np.asarray(a, dtype=float) for a in (times, reliabilities, counts))
    if not (t.shape == ri.shape == ni.shape) or t.size < 2:
        raise ValueError("method S2 needs times, reliabilities and counts of one length >= 2")
    if np.any(t <= 0) or np.any((ri < 0) | (ri > 1)) or np.any(ni <= 0) or not 0 < target < 1:
        raise ValueError("method S2 needs times > 0, reliabilities in [0, 1], counts > 0, 0 < target < 1")

    from scipy import optimize  # here: the daemon's histories mostly have too few calibrations for S2

    def neg_exp(p: np.ndarray) -> float:
        return -_loglik(np.exp(-math.exp(p[0]) * t), ni, ri)

    lam0 = math.log(max(-math.log(max(np.average(ri, weights=ni), 1e-3)) / np.average(t, weights=ni), 1e-12))
    e = optimize.minimize(neg_exp, [lam0], method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-12})
    lam = math.exp(e.x[0])
    models = [S2Model("exponential", (lam,), -math.log(target) / lam, -float(e.fun))]

    def neg_weib(p: np.ndarray) -> float:
        return -_loglik(np.exp(-((math.exp(p[0]) * t) ** math.exp(p[1]))), ni, ri)

    w = optimize.minimize(neg_weib, [e.x[0], 0.0], method="Nelder-Mead",
                          options={"xatol": 1e-10, "fatol": 1e-12, "maxiter": 4000})
    lw, beta = math.exp(w.x[0]), math.exp(w.x[1])
    models.append(S2Model("weibull", (lw, beta), (-math.log(target)) ** (1 / beta) / lw, -float(w.fun)))
    return sorted(models, key=lambda m: -m.log_likelihood)


@dataclass(frozen=True)
class DriftFit:
    """A polynomial drift through the origin, deviation(t) = Σ b_j t^j (j = 1..m), fitted by least
    squares: coefficients, their covariance, the residual standard deviation s_yx and its degrees of
    freedom."""

    coefficients: tuple[float, ...]
    covariance: tuple[tuple[float, ...], ...]
    s_yx: float
    dof: int

    def _basis(self, t: float) -> np.ndarray:
        return np.array([t ** (j + 1) for j in range(len(self.coefficients))])

    def predict(self, t: float) -> float:
        return float(self._basis(t) @ np.asarray(self.coefficients))

    def u_predict(self, t: float) -> float:
        """Standard uncertainty of the fitted drift at t (coefficients' covariance only)."""
        g = self._basis(t)
        return float(math.sqrt(max(g @ np.asarray(self.covariance) @ g, 0.0)))


def fit_drift(times: Sequence[float], deviations: Sequence[float], order: int = 2) -> DriftFit:
    """Least-squares fit of a polynomial through the origin of order ``order`` (see DriftFit)."""
    t, d = np.asarray(times, dtype=float), np.asarray(deviations, dtype=float)
    if t.shape != d.shape or t.size <= order or not np.all(np.isfinite(t)) or not np.all(np.isfinite(d)):
        raise ValueError(f"a drift fit of order {order} needs more than {order} finite (time, deviation) pairs")
    X = np.column_stack([t ** (j + 1) for j in range(order)])
    b, *_ = np.linalg.lstsq(X, d, rcond=None)
    dof = t.size - order
    s2_ = float(np.sum((d - X @ b) ** 2) / dof)
    cov = s2_ * np.linalg.inv(X.T @ X)
    return DriftFit(tuple(float(v) for v in b), tuple(tuple(float(v) for v in row) for row in cov),
                    math.sqrt(s2_), dof)


@dataclass(frozen=True)
class VariablesResult:
    """The variables method: the drift fit and the intervals by the reliability target (the
    prediction's confidence bound reaching a tolerance limit) and by the uncertainty target (the
    prediction's standard uncertainty reaching ``u_target``); NaN where a target is not given, 0 where
    it is not met even at t = 0."""

    fit: DriftFit
    reliability_interval: float
    uncertainty_interval: float


def _u_total(fit: DriftFit, u0: float, t: float) -> float:
    return math.sqrt(u0**2 + fit.s_yx**2 + fit.u_predict(t) ** 2)


def _first_crossing(f: Callable[[float], float], t_max: float) -> float:
    """The smallest t in (0, t_max] where f(t) >= 0 (f continuous), NaN if none."""
    grid = np.linspace(0.0, t_max, 2001)
    vals = np.array([f(x) for x in grid])
    if vals[0] >= 0:
        return 0.0
    idx = np.flatnonzero(vals >= 0)
    if idx.size == 0:
        return math.nan
    from scipy import optimize  # here: only where a crossing is found

    i = int(idx[0])
    return float(optimize.brentq(f, grid[i - 1], grid[i], xtol=1e-10))


def variables(times: Sequence[float], deviations: Sequence[float], *, u0: float, y0: float,
              order: int = 2, limits: tuple[float | None, float | None] | None = None,
              confidence: float = 0.9, u_target: float | None = None,
              t_max: float | None = None) -> VariablesResult:
    """The variables method: as-found deviations (as-found minus the previous as-left) against the
    time since calibration; ``y0`` the as-left value, ``u0`` its standard uncertainty.

    Reliability target: with two limits the confidence is split over both sides (t-quantile of
    (1 + confidence)/2), with one limit it is one-sided; the interval is the first t where
    y0 + drift(t) ± t_q·sqrt(u0² + s_yx² + u_fit(t)²) reaches a limit.  Uncertainty target: the first t
    where sqrt(u0² + s_yx² + u_fit(t)²) reaches ``u_target``."""
    fit = fit_drift(times, deviations, order)
    horizon = t_max if t_max is not None else 10 * float(np.max(times))
    rel = math.nan
    if limits is not None and (limits[0] is not None or limits[1] is not None):
        lo, hi = limits
        two_sided = lo is not None and hi is not None
        tq = float(t_ppf((1 + confidence) / 2 if two_sided else confidence, fit.dof))

        def excess(t: float) -> float:
            y, u = y0 + fit.predict(t), _u_total(fit, u0, t)
            over = (y + tq * u - hi) if hi is not None else -math.inf
            under = (lo - (y - tq * u)) if lo is not None else -math.inf
            return max(over, under)

        rel = _first_crossing(excess, horizon)
    unc = math.nan
    if u_target is not None:
        unc = _first_crossing(lambda t: _u_total(fit, u0, t) - u_target, horizon)
    return VariablesResult(fit, rel, unc)


@dataclass(frozen=True)
class DriftRisk:
    """A linear drift of a parameter against time fitted with its uncertainty, and the probability of
    being outside the tolerance at the due date."""

    slope_per_day: float
    u_slope_per_day: float
    predicted: float
    u_predicted: float
    probability_out_of_tolerance: float


def drift_risk(days: Sequence[float], values: Sequence[float], uncertainties: Sequence[float], *,
               due_day: float, nominal: float, tolerance: float) -> DriftRisk:
    """Weighted straight line (weights 1/u², covariance scaled by the reduced χ² where it exceeds 1)
    through (day, value); the prediction at ``due_day`` with its standard uncertainty, and the normal
    probability that the value then lies outside nominal ± tolerance."""
    t, y, u = (np.asarray(a, dtype=float) for a in (days, values, uncertainties))
    if t.size < 3 or not (t.shape == y.shape == u.shape) or np.any(~np.isfinite(u)) or np.any(u <= 0):
        raise ValueError("a drift risk needs at least 3 values with finite uncertainties > 0")
    if not tolerance > 0:
        raise ValueError("the tolerance must be > 0")
    if not np.ptp(t) > 0:
        raise ValueError("a drift risk needs values at different times")
    W = 1 / u**2
    t0 = float(np.sum(W * t) / np.sum(W))  # the line about its weighted mean time: well conditioned
    X = np.column_stack([np.ones_like(t), t - t0])  # for days counted from 1970 and runs minutes apart
    A = X.T @ (W[:, None] * X)
    cov = np.linalg.inv(A)
    beta = cov @ (X.T @ (W * y))
    chi2 = float(np.sum(W * (y - X @ beta) ** 2) / max(t.size - 2, 1))
    cov = cov * max(chi2, 1.0)
    g = np.array([1.0, due_day - t0])
    pred, u_pred = float(g @ beta), float(math.sqrt(g @ cov @ g))
    p = norm_cdf((nominal - tolerance - pred) / u_pred) + norm_sf((nominal + tolerance - pred) / u_pred)
    return DriftRisk(float(beta[1]), float(math.sqrt(cov[1, 1])), pred, u_pred, float(p))
