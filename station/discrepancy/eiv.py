"""The measured frame motion as the model's input, and what its noise does to the force coefficients.

The model is driven by the frame displacement as recorded: the fundamental X_1 and the harmonics
D_k (k = 2..K) of the displacement channel (``data.x1``, ``data.cd``), whatever their origin (slider
crank, a speed ripple of the drive, ...).  A harmonic the displacement channel does not hold
significantly over the steps (``data.significant_motion``) is taken as zero: the ideal sine's value;
its noise, and the displacement ADC's quantisation residue (with a noise of a third of an LSB the
quantisation error is partly periodic and lands in the harmonics), would only blur or bias the model.
The measurement noise of the harmonics used enters the force model:
the force coefficients of harmonic k move by J_k dD_k with J_k the real 2x2 form of the rig's
transfer H_k = V_k / D_k (V/m) on (a, b) coefficients (phasor a - j b):

    a' = Re(H) a + Im(H) b,   b' = -Im(H) a + Re(H) b.

H_1 is the measured V_1 / X_1; for k >= 2 the stiff model (paper Eq. 9) with the start values of
``base_start`` (the same weights for every model, so that the chi^2 of different models can be
compared).  The whitened force residual w = R_f (c - m) / sigma_f of a step then has covariance
I + A C_D A^T, A = [W_f[:, cols_k] J_k]_k, C_D the covariance of the measured motion coefficients
(fundamental: ``x1_cov``; harmonics: sigma_d^2 (R_d^T R_d)^-1, the marginal covariance of the
harmonic block), and is whitened by chol(I + A C_D A^T)^-1 (errors in variables).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from drivers.rig.model import spring_force_per_acceleration
from drivers.rig.params import Transducer
from station.discrepancy.data import G, RigData
from station.discrepancy.decompose import K_MAX

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]


def base_start(data: RigData) -> dict[str, float]:
    """Start values of S, k_f, b_f, offset from the measured H_i = V_1/X_1 (V/m), stiff model:
    1/H = -(M s^2 + b s + k)/(S M k s^2), i.e. Re(1/H) = -1/(S k) + 1/(S M w^2) and
    Im(1/H) = b/(S M k w): linear least squares in (1/(S k), 1/(S M)) and b/(S M k)."""
    V1 = data.cf[:, 0] - 1j * data.cf[:, 1]
    ok = (V1 != 0) & (data.x1 != 0)  # steps with a measured fundamental (not planned ones)
    inv = data.x1[ok] / V1[ok]
    w = 2 * np.pi * data.f_hz[ok]
    M = data.total_mass_kg
    A = np.column_stack([-np.ones_like(w), 1 / w**2])
    wt = 1 / np.abs(inv)
    (alpha, gamma), *_ = np.linalg.lstsq(A * wt[:, None], inv.real * wt, rcond=None)
    beta = float(np.sum(inv.imag * w * wt**2) / np.sum(wt**2))
    S = 1.0 / (gamma * M)
    k = gamma * M / alpha if alpha * gamma > 0 else 1e3 * M * float(w.max()) ** 2
    b = beta * M / alpha if alpha != 0 else 0.0
    b = b if b > 0 else 1e-3 * math.sqrt(k * M)
    offset = float(np.mean(data.cf[:, 2 * ((data.cf.shape[1] - 3 - 2 * data.n_mains) // 2)])) + S * M * G
    return {"S": float(S), "k_f": float(k), "b_f": float(b), "offset_V": offset}


def measured_motion(data: RigData) -> ComplexArray:
    """Phasors D_k (k = 1..K_MAX) of the recorded frame displacement, (n, K_MAX), m (0 where absent)."""
    D = np.zeros((data.n_steps, K_MAX), dtype=complex)
    D[:, 0] = data.x1
    D[:, 1:] = data.cd[:, 0::2] - 1j * data.cd[:, 1::2]
    return D * data.kmask * data.motion_harmonics()[None, :]


def transfer(data: RigData) -> ComplexArray:
    """H_k (n, K_MAX) in V/m: measured V_1/X_1 for k = 1, the stiff model at the start values above."""
    p = base_start(data)
    t = Transducer(k_f=p["k_f"], b_f=p["b_f"], m_e=data.end_mass_kg, m_l=data.load_mass_kg,
                   sensitivity_V_per_N=p["S"], capacity_N=data.capacity_N)
    f = data.f_hz[:, None] * np.arange(1, K_MAX + 1)[None, :]
    H = p["S"] * spring_force_per_acceleration(t, None, f) * (2j * np.pi * f) ** 2
    H[:, 0] = (data.cf[:, 0] - 1j * data.cf[:, 1]) / np.where(data.x1 == 0, 1.0, data.x1)
    return H


def motion_cov(data: RigData) -> FloatArray:
    """(n, K_MAX, 2, 2): covariance of the measured motion's (a, b) coefficients per harmonic (m^2)."""
    n = data.n_steps
    out = np.zeros((n, K_MAX, 2, 2))
    T = np.diag([1.0, -1.0])
    out[:, 0] = T @ data.x1_cov @ T
    for i in range(n):
        valid = np.nonzero(np.any(data.Rd[i] != 0, axis=0))[0]
        if valid.size == 0:
            continue
        Rv = data.Rd[i][np.ix_(valid, valid)]
        C = data.sigma_d[i] ** 2 * np.linalg.inv(Rv.T @ Rv)
        for j in range(0, valid.size, 2):
            k = valid[j] // 2 + 1  # displacement slots: (a, b) of k = 2..K_MAX
            out[i, k] = C[j : j + 2, j : j + 2]
    return out


def _jac(H: ComplexArray) -> FloatArray:
    J = np.empty((*H.shape, 2, 2))
    J[..., 0, 0], J[..., 0, 1], J[..., 1, 0], J[..., 1, 1] = H.real, H.imag, -H.imag, H.real
    return J


def force_cov(data: RigData) -> FloatArray:
    """(n, K_MAX, 2, 2): covariance the motion noise adds to the force (a, b) coefficients (V^2), for
    the harmonics that drive the model (zero for the others)."""
    J = _jac(transfer(data))
    return J @ motion_cov(data) @ np.swapaxes(J, -1, -2) * data.motion_harmonics()[None, :, None, None]


def whitening(data: RigData, Wf: FloatArray) -> FloatArray:
    """(n, n_f, n_f): chol(I + A C_D A^T)^-1 per step (module docstring), for the whitened force
    residual Wf (c - m)."""
    n, nf = Wf.shape[0], Wf.shape[1]
    J = _jac(transfer(data))
    C = motion_cov(data)
    used = data.motion_harmonics()
    out = np.empty((n, nf, nf))
    for i in range(n):
        M = np.eye(nf)
        for k in range(K_MAX):
            if not (data.kmask[i, k] and used[k]):
                continue
            A = Wf[i][:, 2 * k : 2 * k + 2] @ J[i, k]
            M += A @ C[i, k] @ A.T
        out[i] = np.linalg.inv(np.linalg.cholesky(M))
    return out


def noise_floor(data: RigData) -> float:
    """The gap of a correct model (V): RMS over all windows of the force noise plus the motion noise
    the model takes in with the measured motion (a coefficient error e of a sinusoid adds N e^2 / 2 to
    the window's residual energy): sqrt(sum_s N_s (sigma_s^2 + sum_k tr C_sk / 2) / sum_s N_s)."""
    tr = np.trace(force_cov(data), axis1=-2, axis2=-1) * data.kmask
    e = data.n_samples * (data.sigma_f**2 + 0.5 * tr.sum(axis=1))
    return float(np.sqrt(e.sum() / data.n_samples.sum()))
