"""Recursive least squares in the paper's form (Eq. 17) for the digital model H2 (Eq. 11).

    y(k) = Phi^T theta,  Phi = [-y(k-1), -y(k-2), x(k) + 2 x(k-1) + x(k-2)]^T,
    theta = [a1'/a0', a2'/a0', b0'/a0']^T

Standard RLS (forgetting factor lambda = 1, P0 = delta I).  This is an equation-error (ARX)
estimator: noise on y enters the regressor, which biases theta (the classical ARX bias), and at a
single low frequency the regressors are nearly collinear.  Both explain the paper's poor RLS
testing MSE (Tables 2 and 3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
NEWEY_WEST_LAGS = 2  # the equation error is the output noise through A(q), a 2nd-order MA


@dataclass(frozen=True)
class RlsResult:
    """theta (3,) = (a1'/a0', a2'/a0', b0'/a0'); P (3, 3) final RLS matrix (covariance / sigma^2);
    theta_history (M, 3); b (3,), a (3,) of Eq. 11 with a0' = 1; sigma2: equation-error variance."""

    theta: FloatArray
    P: FloatArray
    theta_history: FloatArray
    b: FloatArray
    a: FloatArray
    sigma2: float


def rls_h2(x: FloatArray, y: FloatArray, *, delta: float = 1e6, lam: float = 1.0) -> RlsResult:
    """Eq. 17 by RLS over all samples k = 2..M-1 (x input, y output, shape (M,))."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    th = np.zeros(3)
    P = delta * np.eye(3)
    hist = np.zeros((x.size, 3))
    errs = []
    for k in range(2, x.size):
        phi = np.array([-y[k - 1], -y[k - 2], x[k] + 2 * x[k - 1] + x[k - 2]])
        e = y[k] - phi @ th
        Pphi = P @ phi
        g = Pphi / (lam + phi @ Pphi)
        th = th + g * e
        P = (P - np.outer(g, Pphi)) / lam
        hist[k] = th
        errs.append(y[k] - phi @ th)
    b0 = th[2]
    return RlsResult(th, P, hist, np.array([b0, 2 * b0, b0]), np.array([1.0, th[0], th[1]]),
                     float(np.mean(np.square(errs))) if errs else float("nan"))


def regressors(x: FloatArray, y: FloatArray) -> FloatArray:
    """Phi (M-2, 3) of Eq. 17, rows k = 2..M-1."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    return np.column_stack([-y[1:-1], -y[:-2], x[2:] + 2 * x[1:-1] + x[:-2]])


def rls_covariance(x: FloatArray, y: FloatArray, r: RlsResult, *, lags: int = NEWEY_WEST_LAGS) -> FloatArray:
    """Covariance (3, 3) of ``r.theta`` as the estimator it is: the sandwich P Omega P with the final RLS
    matrix P = (Phi^T Phi + I / delta)^-1 (its start P0 = delta I acts as a ridge: at one sine frequency
    Phi^T Phi has an eigenvalue near 1/delta, so P, not (Phi^T Phi)^-1, is what shapes theta) and
    Omega the Newey-West (Bartlett, ``lags``) estimate of sum phi_k e_k e_j phi_j^T from the final
    equation errors e = y - Phi theta, which are coloured (the output noise filtered by A(q)) and
    not of one variance.  A white-noise sigma^2 P on such residuals misstates it."""
    phi = regressors(x, y)
    g = phi * (np.asarray(y, float)[2:] - phi @ r.theta)[:, None]
    omega = g.T @ g
    for lag in range(1, min(lags, g.shape[0] - 1) + 1):
        c = g[lag:].T @ g[:-lag]
        omega += (1.0 - lag / (lags + 1)) * (c + c.T)
    return np.asarray(r.P @ omega @ r.P, dtype=np.float64)
