"""Weighted least-squares fit of the rig model (base + a set of effects) to the decomposed steps.

chi^2(theta) = sum_steps ||E W_f (c_f - m_f(theta))||^2, the whitened force coefficients (W_f = R_f /
sigma_f, Gauss-Markov for white noise of the measured sigma).  The model is driven by the measured
frame motion (all its harmonics), whose noise enters the force coefficients: E = chol(I + A C_D A^T)^-1
(errors in variables, ``eiv``; the same weights for every model, so that chi^2 of different models
can be compared).

The time-domain gap of a model is  gap = sqrt(sum_s (ssr_s + sigma_s^2 ||W_f (c_f - m_f)||^2 + ||b_x +
R_x (c_f - m_f)||^2) / sum_s N_s) (the last term: lines outside the catalogue, see ``data``),
the RMS of the force signal minus the simulated force signal over all record windows (V).

The Jacobian: forward differences in the internal variables for the parameters the model depends on
non-linearly (or through a product with another parameter); for the additive ones (the offset, the
zero drift, the per-step mains phasors: m is affine in each, with a coefficient no other parameter
changes) its column is constant and taken once per problem.

Covariance of the estimates: (J^T J)^-1 of the whitened Jacobian, inflated by chi^2/dof when that is
significantly above 1 (p < 1 %; Birge ratio: a model that does not describe the data gets honest,
larger uncertainties).
"""

from __future__ import annotations

import inspect
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.special import chdtrc

from station.discrepancy.catalogue import BASE_PARAMS, NEUTRAL, Param, effect_params, scales
from station.discrepancy.data import RigData, per_data_set
from station.discrepancy.eiv import whitening
from station.discrepancy.model import forces, plan, predict

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ModelFit:
    """A fitted model.

    effects: effect name -> low-pass order (0 for the others); params: the free parameters in fit
    order; values / std: physical values and standard uncertainties by name; cov: (p, p) covariance
    in the order of ``params``; chi2 / n_obs: whitened residual energy and number of coefficients;
    gap_V: RMS force residual over all windows (V); gap_steps_V: per step (n,); wf / wd: whitened force
    (n, n_f) and displacement (n, n_d) residuals (EIV correction not applied), m_f: model force coefs.
    """

    effects: dict[str, int]
    params: tuple[Param, ...]
    values: dict[str, float]
    std: dict[str, float]
    cov: FloatArray
    chi2: float
    n_obs: int
    gap_V: float
    gap_steps_V: FloatArray
    wf: FloatArray
    wd: FloatArray
    m_f: FloatArray
    m_d: FloatArray
    wf_fund: FloatArray
    converged: bool
    notes: tuple[str, ...] = field(default_factory=tuple)
    alternatives: tuple[tuple[int, float, float, float], ...] = ()  # low-pass (order, chi2, k_f, b_f)

    @property
    def n_par(self) -> int:
        """Free parameters (the low-pass order counts as one)."""
        return len(self.params) + (1 if "conditioner_lowpass" in self.effects else 0)

    @property
    def dof(self) -> int:
        return max(self.n_obs - self.n_par, 1)

    @property
    def birge(self) -> float:
        """chi^2 / dof, at least 1."""
        return max(1.0, self.chi2 / self.dof)


@dataclass(frozen=True)
class _Weights:
    """What every model's residual on one data set shares: W_f = R_f / sigma_f (n, n_f, n_f), W_d
    (n, n_d, n_d), the EIV whitening E (n, n_f, n_f), E W_f and E W_f c_f (n, n_f), the force rows
    that hold data (n, n_f)."""

    Wf: FloatArray
    Wd: FloatArray
    eiv: FloatArray
    EW: FloatArray
    EWc: FloatArray
    valid_f: NDArray[np.bool_]


_REL_STEP = math.sqrt(np.finfo(float).eps)


@per_data_set(4)
def _weights(data: RigData) -> _Weights:
    """``_Weights`` once per data set (every model and start point of a recording's analysis shares
    them, ``eiv.whitening`` included)."""
    Wf = data.Rf / data.sigma_f[:, None, None]
    E = whitening(data, Wf)
    # the residual E W_f (c_f - m) as E W_f c_f - (E W_f) m: one product per evaluation
    EW = np.einsum("sij,sjk->sik", E, Wf)
    w = _Weights(Wf=Wf, Wd=data.Rd / data.sigma_d[:, None, None], eiv=E, EW=EW,
                 EWc=np.einsum("sij,sj->si", EW, data.cf), valid_f=np.any(data.Rf != 0, axis=1))
    for a in (w.Wf, w.Wd, w.eiv, w.EW, w.EWc, w.valid_f):
        a.flags.writeable = False
    return w


def _to_value(kind: int, c: float, s: float, u: float) -> float:
    """A parameter's physical value at its fit coordinate ``u``: ``kind`` 0 linear / 1 logarithm /
    2 reciprocal, centre ``c`` and scale ``s`` (``Problem._conversion``)."""
    if kind == 2:
        return 1.0 / (1.0 / c + s * u)
    return c * math.exp(s * u) if kind == 1 else c + s * u


class Problem:
    """The residual function of one model on one data set (internal variables u, see catalogue)."""

    def __init__(self, data: RigData, effects: Mapping[str, int], start: Mapping[str, float]) -> None:
        self.data = data
        self.effects = dict(effects)
        self.params: tuple[Param, ...] = BASE_PARAMS + tuple(
            q for e in self.effects for q in effect_params(e, data))
        # a per-step parameter of a step added by a proposal's plan has no value yet: 0 (all such are linear)
        self.centre = {q.name: float(start[q.name] if q.name in start or q.log or q.reciprocal else 0.0)
                       for q in self.params}
        sc = scales(dict(start), data)
        self.scale = {q.name: sc[q.name] for q in self.params}
        # each parameter's (0 linear / 1 logarithm / 2 reciprocal, centre, scale), made once: ``to_value``
        self._conversion = {q.name: (2 if q.reciprocal else 1 if q.log else 0, self.centre[q.name],
                                     self.scale[q.name]) for q in self.params}
        self._named = tuple((name, *c) for name, c in self._conversion.items())  # (name, kind, centre, scale)
        self.fixed = {**NEUTRAL, **{k: v for k, v in start.items() if k not in self.centre}}
        w = _weights(data)
        self.Wf, self.Wd, self.valid_f = w.Wf, w.Wd, w.valid_f
        # the measured motion is the model's input, not data it is fitted to: no displacement rows
        self.valid_d = np.zeros(data.Rd.shape[:2], dtype=bool)
        # its noise enters the force rows (errors in variables); the same weights for every model
        self.eiv, self.EW, self.EWc = w.eiv, w.EW, w.EWc
        self.additive = tuple(i for i, q in enumerate(self.params) if q.additive)
        self._moved = tuple(i for i, q in enumerate(self.params) if not q.additive)  # forward differences
        self._plan = plan(data, self.effects)  # the model's evaluation on this data set (``model.plan``)
        self._lo, self._hi = self.bounds()
        self._columns: FloatArray | None = None
        self._last: tuple[bytes, FloatArray] | None = None

    def to_value(self, q: Param, u: float) -> float:
        return _to_value(*self._conversion[q.name], u)

    def dvalue(self, q: Param, u: float) -> float:
        if q.reciprocal:
            return -self.scale[q.name] * self.to_value(q, u) ** 2
        return self.to_value(q, u) * self.scale[q.name] if q.log else self.scale[q.name]

    def bounds(self) -> tuple[FloatArray, FloatArray]:
        lo, hi = [], []
        for q in self.params:
            if q.reciprocal:  # 1 / value within [1 / upper, 1 / lower] (both bounds positive)
                c, s = self.centre[q.name], self.scale[q.name]
                lo.append((1.0 / q.upper - 1.0 / c) / s)
                hi.append((1.0 / q.lower - 1.0 / c) / s)
            elif q.log:
                c, s = self.centre[q.name], self.scale[q.name]
                lo.append(math.log(q.lower / c) / s if q.lower > 0 else -np.inf)
                hi.append(math.log(q.upper / c) / s if np.isfinite(q.upper) else np.inf)
            else:
                c, s = self.centre[q.name], self.scale[q.name]
                lo.append((q.lower - c) / s if np.isfinite(q.lower) else -np.inf)
                hi.append((q.upper - c) / s if np.isfinite(q.upper) else np.inf)
        return np.array(lo), np.array(hi)

    def values(self, u: Sequence[float] | FloatArray) -> dict[str, float]:
        """The physical values at u by name (``to_value`` of each parameter, the fixed ones with them)."""
        out = dict(self.fixed)
        for (name, kind, c, s), x in zip(self._named, np.asarray(u, dtype=float).tolist(), strict=True):
            out[name] = _to_value(kind, c, s, x)
        return out

    def whitened(self, p: Mapping[str, float]) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """(wf raw (n, n_f), wd (n, n_d), m_f, m_d) for physical parameters p."""
        m, md, _ = predict(self.data, p, self.effects)
        wf = np.einsum("sij,sj->si", self.Wf, self.data.cf - m)
        wd = np.einsum("sij,sj->si", self.Wd, self.data.cd - md)
        return wf, wd, m, md

    def residual(self, u: Sequence[float] | FloatArray) -> FloatArray:
        """The EIV-whitened force residual rows (the model takes the measured motion as its input:
        no displacement rows, ``valid_d``)."""
        key = np.asarray(u, dtype=float).tobytes()
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        m = forces(self._plan, (self.values(u),))[0]  # ``model.predict``'s force coefficients
        r = (self.EWc - np.einsum("sij,sj->si", self.EW, m))[self.valid_f]
        r.flags.writeable = False
        self._last = (key, r)
        return r

    def _additive_columns(self) -> FloatArray:
        """The constant Jacobian columns of the additive parameters, (n_rows, n_additive): the exact
        difference of a unit step in each (m is affine in it), the steps evaluated together."""
        if self._columns is None:
            r0 = self.residual(np.zeros(len(self.params)))
            at = self.values(np.zeros(len(self.params)))
            steps = [{**at, self.params[j].name: self.to_value(self.params[j], 1.0)} for j in self.additive]
            self._columns = np.ascontiguousarray((self.residuals(steps) - r0).T)
        return self._columns

    def jacobian(self, u: Sequence[float] | FloatArray, step: float | None = None) -> FloatArray:
        """d residual / d u, (n_rows, n_par): forward differences (relative step sqrt(machine
        epsilon) as ``least_squares`` takes them, reversed at an upper bound; or the absolute
        ``step``) for the non-additive parameters, the constant columns for the additive ones."""
        x = np.asarray(u, dtype=float)
        r0 = self.residual(x)
        J = np.empty((r0.size, x.size))
        if self.additive:
            J[:, list(self.additive)] = self._additive_columns()
        lo, hi = self._lo.tolist(), self._hi.tolist()
        cols = list(self._moved)
        at = self.values(x)
        xs = x.tolist()  # the same doubles as Python floats (the same arithmetic, less overhead)
        points, steps = [], []
        for j in cols:
            xj0 = xs[j]
            if step is None:
                h = _REL_STEP * (1.0 if xj0 >= 0 else -1.0) * max(1.0, abs(xj0))
                if not lo[j] <= xj0 + h <= hi[j] and lo[j] <= xj0 - h <= hi[j]:
                    h = -h
            else:
                h = step
            xj = xj0 + h
            name, kind, c, s = self._named[j]
            points.append({**at, name: _to_value(kind, c, s, xj)})  # the values at x with u_j moved
            steps.append(xj - xj0)
        if cols:
            J[:, cols] = ((self.residuals(points) - r0) / np.array(steps)[:, None]).T
        return J

    def residuals(self, ps: Sequence[Mapping[str, float]]) -> FloatArray:
        """``residual`` for several sets of physical parameters at once, (P, n_rows): the same values,
        the model evaluated for all of them together (``model.forces``)."""
        m = forces(self._plan, ps)
        return (self.EWc[None] - np.einsum("sij,psj->psi", self.EW, m))[:, self.valid_f]

    def n_obs(self) -> int:
        return int(self.valid_f.sum() + self.valid_d.sum())


def gap_of(data: RigData, wf: FloatArray, m: FloatArray) -> tuple[float, FloatArray]:
    """(overall, per-step) RMS force residual in V from the raw whitened force residual wf and the
    model coefficients m (for the rows of the lines outside the catalogue, which no model explains)."""
    ex = data.bx + np.einsum("sij,sj->si", data.Rx, data.cf - m)
    e = data.ssr_f + data.sigma_f**2 * np.sum(wf**2, axis=1) + np.sum(ex**2, axis=1)
    return float(math.sqrt(e.sum() / data.n_samples.sum())), np.sqrt(e / data.n_samples)


_FITS: dict[int, tuple[RigData, dict[tuple[object, ...], ModelFit | None]]] = {}
MAX_NFEV = 400
# The fits' stopping rule: ``least_squares`` (trust-region reflective) stops when an accepted step lowers
# chi^2 by less than ftol of chi^2, moves u by less than xtol of |u|, or the scaled gradient is below
# gtol.  Chosen from a sweep over the model-gap test files' 2 518 fits (docs/discrepancy.md, Bench): ftol
# is relative to chi^2, and a start far from the data (chi^2 1e7-1e10) whose first steps gain less than
# ftol of that stops there as converged.  With (ftol, gtol, xtol) = (1e-8, 1e-8, 1e-6) 21 fits ended more
# than 1 (up to 1e9) above where these take them and a sensor-resonance run named the delay it ties with;
# (1e-7, 1e-7, 1e-5) 22 fits (up to 1e10); a stop once the Gauss-Newton step promises less than 1e-3 B
# (B = max(1, chi^2/dof)) saved 6 % of the evaluations but moved reported parameters by more than 0.01 std.
STOPPING_RULE = {"ftol": 1e-10, "gtol": 1e-10, "xtol": 1e-8}
# least_squares takes a callback from SciPy 1.16 on; with an older SciPy (the floor is 1.11) no fit is
# given up, and every fit runs as fit_model's: the same results, only the shortcut is lost
CAN_GIVE_UP = "callback" in inspect.signature(least_squares).parameters


def _kept(data: RigData) -> dict[tuple[object, ...], ModelFit | None]:
    """The fits kept for ``data`` (a new, empty set replaces the oldest data set's beyond four)."""
    hit = _FITS.get(id(data))
    if hit is None or hit[0] is not data:
        if len(_FITS) >= 4:
            del _FITS[next(iter(_FITS))]  # the oldest data set
        hit = _FITS[id(data)] = (data, {})
    return hit[1]


def _fit_key(effects: Mapping[str, int], start: Mapping[str, float], max_nfev: int) -> tuple[object, ...]:
    return tuple(effects.items()), tuple(sorted(start.items())), max_nfev


def fit_model(data: RigData, effects: Mapping[str, int], start: Mapping[str, float],
              max_nfev: int = MAX_NFEV) -> ModelFit:
    """Levenberg-Marquardt (trust-region) fit of base + effects from ``start`` (physical values).

    The fit is a function of its arguments: one analysis asks for the same fit several times (the
    ties, the proposal and the swap test refit the same reduced model and its candidates), so the
    fits of the few most recent data sets are kept and given again (frozen, never modified)."""
    kept = _kept(data)
    key = _fit_key(effects, start, max_nfev)
    fit = kept.get(key)
    if fit is None:
        fit = kept[key] = _fit_model(data, effects, start, max_nfev)
    return fit


class _GivenUp(Exception):
    """A fit halted by ``fit_unless_above``'s check."""


def fit_unless_above(data: RigData, effects: Mapping[str, int], start: Mapping[str, float], chi2: float,
                     after: int) -> ModelFit | None:
    """``fit_model``, given up (None) if after ``after`` model evaluations its chi^2 is still at or
    above ``chi2``.  A fit that is not given up is exactly ``fit_model``'s (the check looks at each
    iterate and changes none) and is kept as ``fit_model``'s."""
    kept = _kept(data)
    key = _fit_key(effects, start, MAX_NFEV)
    if key in kept:
        return kept[key]
    if not CAN_GIVE_UP:
        return fit_model(data, effects, start)
    mark = (*key, "given up above", chi2, after)
    if mark in kept:
        return None

    def check(intermediate_result: Any) -> None:  # so named, scipy passes the iterate's state
        if intermediate_result.nfev >= after and 2.0 * float(intermediate_result.cost) >= chi2:
            raise StopIteration

    try:
        kept[key] = _fit_model(data, effects, start, MAX_NFEV, check)
    except _GivenUp:
        kept[mark] = None
        return None
    return kept[key]


def _fit_model(data: RigData, effects: Mapping[str, int], start: Mapping[str, float],
               max_nfev: int, callback: Callable[[Any], None] | None = None) -> ModelFit:
    prob = Problem(data, effects, start)
    lo, hi = prob.bounds()
    u0 = np.clip(np.zeros(len(prob.params)), lo, hi)
    halt = {} if callback is None else {"callback": callback}
    res = least_squares(prob.residual, u0, jac=prob.jacobian, bounds=(lo, hi), method="trf", x_scale=1.0,
                        max_nfev=max_nfev, **STOPPING_RULE, **halt)
    if res.status == -2:  # halted by the callback
        raise _GivenUp
    return finish(prob, res.x, res.jac, bool(res.success))


def finish(prob: Problem, u: FloatArray, jac: FloatArray, converged: bool) -> ModelFit:
    """Package a solution: values, covariance (Birge-inflated), gap."""
    vals = prob.values(u)
    r = prob.residual(u)
    chi2 = float(r @ r)
    n_obs = prob.n_obs()
    D = np.array([prob.dvalue(q, float(x)) for q, x in zip(prob.params, u, strict=True)])
    JtJ = jac.T @ jac
    try:
        cov_u = np.linalg.inv(JtJ)
    except np.linalg.LinAlgError:
        cov_u = np.linalg.pinv(JtJ)
    n_par = len(prob.params) + (1 if "conditioner_lowpass" in prob.effects else 0)
    dof = max(n_obs - n_par, 1)
    # inflate only when the misfit is significant (p < 1 %), not for chance chi^2/dof slightly above 1
    birge = chi2 / dof if chdtrc(dof, chi2) < 0.01 else 1.0
    cov = birge * (D[:, None] * cov_u * D[None, :])
    std = {q.name: float(math.sqrt(max(cov[i, i], 0.0))) for i, q in enumerate(prob.params)}
    wf, wd, m, md = prob.whitened(vals)
    gap, gap_steps = gap_of(prob.data, wf, m)
    wf_fund = np.einsum("sij,sj->si", prob.eiv, wf)[:, 0:2]
    notes = () if birge <= 1.0 else (f"uncertainties inflated by sqrt(chi2/dof) = {math.sqrt(birge):.3g}",)
    return ModelFit(effects=dict(prob.effects), params=prob.params, values=vals, std=std, cov=cov,
                    chi2=chi2, n_obs=n_obs, gap_V=gap, gap_steps_V=gap_steps, wf=wf, wd=wd, m_f=m,
                    m_d=md, wf_fund=wf_fund, converged=converged, notes=notes)


def profiled_chi2(prob: Problem, u: FloatArray, eps: float = 1e-4) -> float:
    """chi^2 minimised over all free parameters to first order around u: ||(I - P_J) r||^2 with J
    the numerical Jacobian (forward differences of step eps in u).  Exact for linear parameters."""
    r0 = prob.residual(u)
    J = prob.jacobian(u, step=eps)
    coef, *_ = np.linalg.lstsq(J, r0, rcond=None)
    r = r0 - J @ coef
    return float(r @ r)
