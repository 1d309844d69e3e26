"""Time-domain output-error refinement on the raw force samples of every step.

Model of the force signal in step i (t from the step's window centre):

    U_i(t) = c_i + sum_h Re( H(h w_i; theta) A_{i,h} e^{j h w_i t} )

where A_{i,h} are the acceleration phasors of the frame motion (fundamental and crank
harmonics h = 1..n_h) from the displacement sine fit (A = -(h w)^2 X).  theta and the offsets c_i
are fitted by Levenberg-Marquardt to all force samples (Eq. 15 summed over steps).  Compared with
the frequency-domain fit this uses the samples directly (no intermediate force phasor) and the
harmonics of the crank motion as extra excitation.  Covariance: s^2 (J^T J)^-1 with s^2 the
residual variance, plus the displacement-phasor covariance propagated through the estimate
(G C_X G^T, G = -(J^T J)^-1 J^T dr/dX; fundamental only): at high frequency the acceleration,
not the force, limits the accuracy.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from station.ident.fd.core import start_values
from station.ident.fd.identify import identify_fd
from station.ident.identifiability import Policy
from station.ident.inputs import IdentInputs, inputs_for, model_for
from station.ident.models import Model, SdofModel
from station.ident.response import frf as frfmod
from station.ident.response.checked import StepSignal, checked_response
from station.ident.result import FitSummary, IdentificationResult, estimated_covariance, estimates
from station.ident.uncertainty import ParameterBudget, UncertaintyBudget
from station.recording import Recording

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class OeFit:
    """theta (n,), cov (n, n) in model units; offsets (n_steps,) in V; residual RMS per step (V);
    mse in V^2 over all samples; jac_rel: Jacobian d(residual/s)/d(ln theta), (N_total, n)."""

    theta: FloatArray
    cov: FloatArray
    offsets_V: FloatArray
    residual_rms_V: FloatArray
    mse: float
    jac_rel: FloatArray


def fit_oe(steps: list[StepSignal], model: Model, theta0: FloatArray,
           free: NDArray[np.bool_] | None = None) -> OeFit:
    """Output-error LM fit of the free parameters (others held at theta0) and per-step offsets."""
    theta0 = np.asarray(theta0, float)
    free = np.ones(theta0.size, bool) if free is None else np.asarray(free, bool)
    nf = int(free.sum())
    basis = []
    for st in steps:
        w = 2 * np.pi * st.fit_x.frequency_hz
        tt = st.t - st.fit_x.t_center_s
        h = np.arange(1, st.X_h.size + 1)
        A = -((h * w) ** 2) * st.X_h
        basis.append((h * st.fit_x.frequency_hz, A, np.exp(1j * np.outer(tt, h * w))))

    def theta_of(p: FloatArray) -> FloatArray:
        th = theta0.copy()
        th[free] = theta0[free] * np.exp(p[:nf])
        return th

    def resid(p: FloatArray) -> FloatArray:
        th = theta_of(p)
        out = []
        for i, (st, (fh, A, E)) in enumerate(zip(steps, basis, strict=True)):
            out.append(p[nf + i] + (E @ (model.response(th, fh) * A)).real - st.u)
        return np.concatenate(out)

    def jac(p: FloatArray) -> FloatArray:
        th = theta_of(p)
        rows = []
        for i, (fh, A, E) in enumerate(basis):
            Jh = model.jacobian(th, fh) * th[None, :]
            blk = np.zeros((E.shape[0], nf + len(steps)))
            blk[:, :nf] = (E @ (Jh[:, free] * A[:, None])).real
            blk[:, nf + i] = 1.0
            rows.append(blk)
        return np.vstack(rows)

    from scipy.optimize import least_squares  # here: importing the module (a report does) fits nothing

    p0 = np.concatenate([np.zeros(nf), [float(np.mean(st.u)) for st in steps]])
    sol = least_squares(resid, p0, jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    r = sol.fun
    N = r.size
    s2 = float(r @ r) / max(N - p0.size, 1)
    J = jac(sol.x)
    JtJi = np.linalg.inv(J.T @ J)
    cov_p = s2 * JtJi
    theta = theta_of(sol.x)
    # input (displacement phasor) noise: p moves by G dX, G = -(J^T J)^-1 J^T dr/dX
    Jx = np.zeros((N, 2 * len(steps)))
    edges0 = np.cumsum([0] + [st.t.size for st in steps])
    for i, (fh, _A, E) in enumerate(basis):
        Hw = model.response(theta, fh[:1])[0] * -((2 * np.pi * fh[0]) ** 2)
        col = E[:, 0] * Hw
        Jx[edges0[i]:edges0[i + 1], 2 * i] = col.real
        Jx[edges0[i]:edges0[i + 1], 2 * i + 1] = (1j * col).real
    G = -JtJi @ (J.T @ Jx)
    Cx = np.zeros((2 * len(steps), 2 * len(steps)))
    for i, st in enumerate(steps):
        Cx[2 * i:2 * i + 2, 2 * i:2 * i + 2] = st.fit_x.phasor_cov
    cov_p = cov_p + G @ Cx @ G.T
    idx = np.nonzero(free)[0]
    cov = np.zeros((theta.size, theta.size))
    cov[np.ix_(idx, idx)] = cov_p[:nf, :nf] * np.outer(theta[idx], theta[idx])
    edges = np.cumsum([0] + [st.t.size for st in steps])
    rms = np.array([np.sqrt(np.mean(r[a:b] ** 2)) for a, b in itertools.pairwise(edges)])
    return OeFit(theta, cov, sol.x[nf:], rms, float(np.mean(r**2)), J[:, :nf] / np.sqrt(s2))


def identify_oe(rec: Recording, model_key: str = "sdof", policy: Policy | None = None,
                inputs: IdentInputs | None = None) -> IdentificationResult:
    """Time-domain output error on the raw force samples, started from the FD estimate."""
    inputs = inputs or inputs_for(rec)
    cr = checked_response(rec, inputs)
    frf, sigs, notes = cr.frf, cr.sigs, []
    model = model_for(rec, "coupled" if model_key in ("coupled", "h1") else "sdof", inputs)
    fd = identify_fd(rec, model.key, policy, inputs=inputs, response=cr)  # one checked H(f)
    ok = np.array(fd.identifiability.identifiable) if fd.identifiability else np.ones(len(model.names), bool)
    sd = model_for(rec, "sdof", inputs)
    assert isinstance(sd, SdofModel)
    th0 = frfmod.fit_frf(frf, sd, start_values(frf, sd, cr.sign)).theta
    if model.key == "coupled":
        th0 = np.r_[th0, 10 * th0[1], 0.1 * th0[2]]
        if not ok[3]:
            model, ok, th0 = sd, ok[:3], th0[:3]
    fit = fit_oe(sigs, model, th0, free=ok)
    rep = fd.identifiability
    ident = tuple(bool(v) for v in ok)
    reasons = rep.reasons[: len(ident)] if rep else ("",) * len(ident)
    params = estimates(model.names, model.units, fit.theta, fit.cov, ident, reasons)
    covariance = estimated_covariance(params, model.names, fit.cov)  # correlations of the OE fit
    budget: dict[str, ParameterBudget] = {}
    for name, p in params.items():  # OE's own noise term, the systematic terms of the FD budget
        b = fd.budget.get(name)
        if p.identifiable and name in fd.parameters and not fd.parameter(name).identifiable:
            params[name] = fd.parameter(name)  # withheld by the FD result's structure (e.g. coupling_suspected)
            continue
        if b is None or not p.identifiable or p.std is None:
            continue
        budget[name] = b.with_contribution("noise", p.std)
        comb = budget[name].combined
        fdp = fd.parameter(name)
        params[name] = replace(p, std=comb, flag=fdp.flag, reason=fdp.reason if fdp.flag else p.reason)
    if covariance is not None:  # the same correlations at the combined standard uncertainties
        covariance = estimated_covariance(params, covariance.names, covariance.array)
    if len(params) < len(fd.parameters):
        params.update({n: p for n, p in fd.parameters.items() if n not in params})
        notes.append("k_c, b_c not identifiable: OE fit in the stiff-coupling limit (Eq. 9)")
    summary = FitSummary(fit.mse, tuple(float(v) for v in fit.residual_rms_V), float("nan"),
                         int(sum(s.t.size for s in sigs)))
    return IdentificationResult("oe", fd.model, params, summary, rep, tuple(notes),
                                {"offsets_V": fit.offsets_V.tolist()}, fd.checks,
                                UncertaintyBudget(budget), fd.assumptions,
                                fd.determined, covariance)
