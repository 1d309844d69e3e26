"""Least-squares sine fits (IEEE 1057 three- and four-parameter, ISO 16063-11 style).

Model of one channel over one step, t in s measured from the window centre t_c:

    x(t) = Re(X e^{j w t}) + C + sum_{h=2..n_h} Re(X_h e^{j h w t}),   X = A - jB

i.e. x = A cos(w t) + B sin(w t) + C (+ harmonics, which the crank mechanism produces and which
are orthogonal nuisance terms).  Three-parameter fit: w known, linear LS.  Four-parameter fit:
w estimated too (Gauss-Newton from a three-parameter start, IEEE 1057 Sec. 4.1.3.3).  The phasor
covariance is s^2 (J^T J)^-1 with s^2 the residual variance (for white noise of variance sigma^2
and whole periods, var(A) = var(B) = 2 sigma^2 / N).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SineFit:
    """Result of a sine fit of one channel.

    frequency_hz / frequency_std_hz: fitted (4-par) or given (3-par, std 0);
    phasor: complex amplitude X at the window centre (channel unit); phasor_cov: 2 x 2 covariance
    of (Re X, Im X); offset / offset_std: C; residual_rms: RMS residual (channel unit);
    n_samples: samples used; t_center_s: time origin of the phasor; harmonics: phasors of the
    harmonics 2..n_h (channel unit), same time origin.
    """

    frequency_hz: float
    frequency_std_hz: float
    phasor: complex
    phasor_cov: FloatArray
    offset: float
    offset_std: float
    residual_rms: float
    n_samples: int
    t_center_s: float
    harmonics: tuple[complex, ...] = ()


def _design(t: FloatArray, w: float, n_harmonics: int) -> FloatArray:
    cols = [np.cos(w * t), np.sin(w * t), np.ones_like(t)]
    for h in range(2, n_harmonics + 1):
        cols += [np.cos(h * w * t), np.sin(h * w * t)]
    return np.column_stack(cols)


def _finish(y: FloatArray, J: FloatArray, p: FloatArray, f_hz: float, f_std: float,
            tc: float, cov_extra: FloatArray | None = None, n_harmonics: int = 1) -> SineFit:
    r = y - J @ p
    dof = max(y.size - J.shape[1], 1)
    s2 = float(r @ r) / dof
    cov = s2 * np.linalg.inv(J.T @ J) if cov_extra is None else cov_extra * s2
    # X = A - jB: cov of (Re, Im) = cov of (A, -B)
    T = np.array([[1.0, 0.0], [0.0, -1.0]])
    pc = T @ cov[:2, :2] @ T.T
    harm = tuple(complex(p[3 + 2 * k], -p[4 + 2 * k]) for k in range(n_harmonics - 1))
    return SineFit(f_hz, f_std, complex(p[0], -p[1]), pc, float(p[2]), float(np.sqrt(cov[2, 2])),
                   float(np.sqrt(np.mean(r**2))), int(y.size), tc, harm)


def fit3(t: FloatArray, y: FloatArray, f_hz: float, *, t_center_s: float | None = None,
         n_harmonics: int = 1) -> SineFit:
    """Three-parameter sine fit (IEEE 1057 4.1.3.1) at known frequency f_hz.

    t: sample times in s, shape (N,); y: samples, shape (N,); n_harmonics: highest harmonic fitted
    as nuisance (1 = fundamental only).
    """
    t = np.asarray(t, float)
    y = np.asarray(y, float)
    tc = float(np.mean(t)) if t_center_s is None else t_center_s
    J = _design(t - tc, 2 * np.pi * f_hz, n_harmonics)
    p = np.linalg.lstsq(J, y, rcond=None)[0]
    return _finish(y, J, p, f_hz, 0.0, tc, n_harmonics=n_harmonics)


def fit4(t: FloatArray, y: FloatArray, f0_hz: float, *, t_center_s: float | None = None,
         n_harmonics: int = 1, max_iter: int = 20) -> SineFit:
    """Four-parameter sine fit (IEEE 1057 4.1.3.3): Gauss-Newton on (A, B, C, [harmonics], w)
    from a three-parameter fit at the start frequency f0_hz (in Hz)."""
    t = np.asarray(t, float)
    y = np.asarray(y, float)
    tc = float(np.mean(t)) if t_center_s is None else t_center_s
    tt = t - tc
    w = 2 * np.pi * f0_hz
    J0 = _design(tt, w, n_harmonics)
    p = np.linalg.lstsq(J0, y, rcond=None)[0]
    for _ in range(max_iter):
        J0 = _design(tt, w, n_harmonics)
        dw = -p[0] * tt * np.sin(w * tt) + p[1] * tt * np.cos(w * tt)
        for h in range(2, n_harmonics + 1):
            a, b = p[3 + 2 * (h - 2)], p[4 + 2 * (h - 2)]
            dw += h * tt * (-a * np.sin(h * w * tt) + b * np.cos(h * w * tt))
        J = np.column_stack([J0, dw])
        r = y - J0 @ p
        step = np.linalg.lstsq(J, r, rcond=None)[0]
        p = p + step[:-1]
        w += step[-1]
        if abs(step[-1]) < 1e-12 * w:
            break
    J0 = _design(tt, w, n_harmonics)
    dw = -p[0] * tt * np.sin(w * tt) + p[1] * tt * np.cos(w * tt)
    J = np.column_stack([J0, dw])
    cov = np.linalg.inv(J.T @ J)
    fit = _finish(y, J, np.append(p, 0.0), w / (2 * np.pi), 0.0, tc, cov_extra=cov,
                  n_harmonics=n_harmonics)
    r = y - J0 @ p
    s2 = float(r @ r) / max(y.size - J.shape[1], 1)
    f_std = float(np.sqrt(cov[-1, -1] * s2)) / (2 * np.pi)
    return SineFit(fit.frequency_hz, f_std, fit.phasor, fit.phasor_cov, fit.offset, fit.offset_std,
                   float(np.sqrt(np.mean(r**2))), fit.n_samples, tc, fit.harmonics)
