"""Which parameters can the data determine?  Structural and practical identifiability.

1. Structural: one steady sine carries two real numbers (gain and phase of H), so n_f distinct
   frequencies determine at most 2 n_f real parameters.  Numerically: the SVD of the whitened,
   parameter-relative Jacobian; a parameter with a loading > ``null_loading`` on the (numerical)
   null space is not identifiable.
2. Practical: with the structurally identifiable set, the relative standard uncertainty must be
   below ``max_rel_std``.  For this decision the statistical covariance of H is augmented by a
   floor for what a measurement chain typically gets wrong: a frequency-independent phase error of
   ``phase_floor_rad`` and a relative gain error ``gain_floor`` at each frequency.  At 4 Hz the
   damping of a force transducer shows only as a fraction of a degree of phase, the size of an
   amplifier's or ADC's own phase error, so it is reported as not identifiable.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from station.ident.models import Model
from station.ident.response.frf import FrequencyResponse, whitened_jacobian
from station.ident.result import Identifiability

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Policy:
    """Decision thresholds: null_loading (dimensionless), max_rel_std (dimensionless),
    phase_floor_rad (rad), gain_floor (relative), rank_tol (relative singular value)."""

    null_loading: float = 0.1
    max_rel_std: float = 0.1
    phase_floor_rad: float = float(np.deg2rad(0.1))
    gain_floor: float = 1e-4
    rank_tol: float = 1e-9


def floor_cov(frf: FrequencyResponse, policy: Policy) -> FloatArray:
    """cov of (Re H, Im H) plus the chain floor: H (g + j phi), g ~ gain_floor, phi ~ phase floor."""
    out = frf.cov.copy()
    for i, H in enumerate(frf.H):
        R = np.array([[H.real, -H.imag], [H.imag, H.real]])
        out[i] += R @ np.diag([policy.gain_floor**2, policy.phase_floor_rad**2]) @ R.T
    return out


def correlations(cov: FloatArray) -> FloatArray:
    """Correlation matrix of a covariance (zeros where a variance is 0)."""
    s = np.sqrt(np.clip(np.diag(cov), 0, None))
    with np.errstate(all="ignore"):
        c: FloatArray = cov / np.outer(s, s)
    c[~np.isfinite(c)] = 0.0
    return c


def structural_null(J: FloatArray, policy: Policy,
                    n_data_dims: int | None = None) -> tuple[NDArray[np.bool_], float]:
    """Parameters loading on the null space of J (m, n), and the condition number.

    The null space holds the directions with singular value <= rank_tol * largest and, when the
    data carry only ``n_data_dims`` real numbers (2 per sine frequency), the n - n_data_dims
    weakest directions whatever their singular values (transients and rounding make them nonzero)."""
    n = J.shape[1]
    _, sv, Vt = np.linalg.svd(J, full_matrices=True)
    svf = np.zeros(n)
    svf[: sv.size] = sv
    null = svf <= policy.rank_tol * svf[0]
    if n_data_dims is not None and n_data_dims < n:
        null[n_data_dims:] = True
    cond = float(svf[0] / svf[-1]) if svf[-1] > 0 else float("inf")
    if not null.any():
        return np.zeros(n, bool), cond
    N = Vt[null]  # rows spanning the null space
    return np.sqrt(np.sum(N**2, axis=0)) > policy.null_loading, cond


def structural_reasons(names: tuple[str, ...], bad: NDArray[np.bool_], n_f: int) -> list[str]:
    """Reason strings ('' for fine) for structurally non-identifiable parameters."""
    out = [""] * len(names)
    for i in np.nonzero(bad)[0]:
        freq = "frequency gives" if n_f == 1 else "frequencies give"
        out[i] = (f"structurally not identifiable: {n_f} sine {freq} "
                  f"{2 * n_f} real numbers (gain and phase) for {len(names)} parameters; "
                  f"{names[i]} is confounded with "
                  + ", ".join(nm for j, nm in enumerate(names) if j != i))
    return out


def effect_text(model: Model, theta: FloatArray, f_hz: FloatArray, i: int) -> str:
    """How much a 100 % change of parameter i moves |H| (relative) and arg H (deg), at most."""
    eff = model.jacobian(theta, f_hz)[:, i] * theta[i] / model.response(theta, f_hz)
    return (f"a 100 % change of {model.names[i]} moves |H| by at most {np.max(np.abs(eff.real)):.2g} "
            f"(relative) and the phase by at most {np.rad2deg(np.max(np.abs(eff.imag))):.2g} deg "
            f"at {', '.join(f'{f:g}' for f in np.unique(np.round(f_hz, 3)))} Hz")


def regularised_cov(J: FloatArray) -> FloatArray:
    """(J^T J + eps I)^-1 with eps = 1e-12 |J|^2: finite even when J is rank deficient, so that the
    correlations of confounded parameters show as +-1."""
    JtJ = J.T @ J
    return np.linalg.inv(JtJ + 1e-12 * np.trace(JtJ) * np.eye(JtJ.shape[0]))


def assess(model: Model, theta: FloatArray, frf: FrequencyResponse, policy: Policy = Policy(),
           scale: FloatArray | None = None) -> tuple[Identifiability, NDArray[np.bool_]]:
    """Identifiability of every model parameter from a measured frequency response.

    scale: typical parameter values (default |theta|); uncertainties are judged relative to it.
    Returns the report and the mask of structurally identifiable parameters (to fit)."""
    names = model.names
    n_f = int(np.unique(np.round(frf.f_hz, 6)).size)
    J = whitened_jacobian(model, theta, frf, floor_cov(frf, policy), scale)
    struct_bad, cond = structural_null(J, policy, 2 * n_f)
    reasons = structural_reasons(names, struct_bad, n_f)
    for i in np.nonzero(struct_bad)[0]:
        reasons[i] += "; " + effect_text(model, theta, frf.f_hz, int(i))
    ok = ~struct_bad
    Jok = J[:, ok]
    cov_rel = np.linalg.pinv(Jok.T @ Jok) if ok.any() else np.zeros((0, 0))
    rel_std = np.full(len(names), np.inf)
    rel_std[ok] = np.sqrt(np.diag(cov_rel))
    for i in np.nonzero(ok)[0]:
        if rel_std[i] > policy.max_rel_std:
            reasons[i] = (f"not identifiable in practice: relative uncertainty {rel_std[i]:.2g} "
                          f"(> {policy.max_rel_std}) with a chain floor of "
                          f"{np.rad2deg(policy.phase_floor_rad):.2g} deg phase and {policy.gain_floor:.1g} "
                          f"gain; " + effect_text(model, theta, frf.f_hz, int(i)))
    identifiable = np.array([r == "" for r in reasons])
    corr = correlations(regularised_cov(J))
    rep = Identifiability(names, cond, tuple(tuple(float(c) for c in row) for row in corr),
                          tuple(bool(b) for b in identifiable), tuple(reasons))
    return rep, ok


def carried_to_determined(model: Model, theta: FloatArray, frf: FrequencyResponse, determined: tuple[bool, ...],
                          cov_undetermined: FloatArray) -> FloatArray:
    """The uncertainty of the parameters the data do not determine, carried to those they do at
    fixed H(f): d_ok = -pinv(J_ok) J_nk d_nk (J the whitened Jacobian of H at ``frf``'s
    frequencies), so cov_ok = D C_nk D^T; shape (n, n), zero outside the determined block.

    A determined parameter's noise-only covariance (J_ok^T J_ok)^-1 is conditional on the others held
    at the estimate; this is the term that removes the condition.  cov_undetermined (n, n): the
    estimator's own covariance of all parameters (only its undetermined block is read).  Where that
    is unknown (non-finite) the determined parameters that depend on it get NaN: their uncertainty
    cannot be stated, and the caller must withhold them rather than state the conditional one."""
    ok = np.asarray(determined, dtype=bool)
    n = theta.size
    out = np.zeros((n, n))
    if not (ok.any() and (~ok).any()):
        return out
    J = whitened_jacobian(model, theta, frf, scale=np.ones(n))
    D = -np.linalg.pinv(J[:, ok]) @ J[:, ~ok]
    C = np.asarray(cov_undetermined, dtype=np.float64)[np.ix_(~ok, ~ok)]
    if np.all(np.isfinite(C)):
        out[np.ix_(ok, ok)] = D @ C @ D.T
    else:
        idx = np.flatnonzero(ok)[np.any(D != 0, axis=1)]
        out[idx, idx] = np.nan
    return out
