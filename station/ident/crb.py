"""Cramér-Rao bound for the physical parameters from stepped-sine records.

Data per step i (frequency f_i, N_i samples, white noise): displacement x = Re(X_i e^{jwt}) + n_x,
force U = Re(H(f_i; theta) A_i e^{jwt}) + n_u, A_i = -w_i^2 X_i, var(n_x) = sigma_x^2 (m^2),
var(n_u) = sigma_u^2 (V^2); offsets and harmonics are orthogonal nuisance parameters.

Sufficient statistics are the two fitted phasors; each quadrature component of a phasor has
variance 2 sigma^2 / N.  With the true acceleration phasor A_i as a nuisance (errors in both
channels), the Schur complement of the Fisher information eliminates it exactly and leaves, per
step, circular Gaussian information about H_i with variance per component

    s_i^2 = (2 / N_i) (sigma_u^2 + |H_i|^2 w_i^4 sigma_x^2) / |A_i|^2.

So F(theta) = sum_i J_i^T J_i / s_i^2, J_i = (Re, Im) dH/dtheta (2 x n), and CRB = F^-1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from station.ident.models import Model

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class CramerRaoBound:
    """cov: bound on the covariance of unbiased estimates of theta (model units), (n, n);
    std: sqrt of its diagonal (n,); names: parameter names."""

    names: tuple[str, ...]
    cov: FloatArray
    std: FloatArray


def h_variance(model: Model, theta: ArrayLike, f_hz: ArrayLike, n_samples: ArrayLike,
               displacement_amplitude_m: ArrayLike, sigma_x_m: float, sigma_u_V: float) -> FloatArray:
    """Per-component variance s_i^2 of H_i in (V/(m/s^2))^2, shape (n_f,)."""
    f = np.asarray(f_hz, float)
    w2 = (2 * np.pi * f) ** 2
    H = model.response(theta, f)
    A = w2 * np.asarray(displacement_amplitude_m, float)
    var: FloatArray = 2.0 / np.asarray(n_samples, float) * (sigma_u_V**2 + np.abs(H) ** 2 * w2**2 * sigma_x_m**2) / A**2
    return var


def crb_stepped_sine(model: Model, theta: ArrayLike, f_hz: ArrayLike, n_samples: ArrayLike,
                     displacement_amplitude_m: ArrayLike, sigma_x_m: float,
                     sigma_u_V: float) -> CramerRaoBound:
    """CRB of theta for a stepped-sine run (see module docstring)."""
    th = np.asarray(theta, float)
    f = np.asarray(f_hz, float)
    s2 = h_variance(model, th, f, n_samples, displacement_amplitude_m, sigma_x_m, sigma_u_V)
    J = model.jacobian(th, f)
    F = (J.real.T / s2) @ J.real + (J.imag.T / s2) @ J.imag
    cov = np.asarray(np.linalg.inv(F), dtype=np.float64)
    return CramerRaoBound(model.names, cov, np.sqrt(np.diag(cov)))
