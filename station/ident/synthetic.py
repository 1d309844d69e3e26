"""Exact steady-state stepped-sine data from the continuous models (for tests and benchmarks).

Step i: x(t) = r_i sin(w_i t + phi_i) + n_x,  U(t) = c + Re(H(j w_i) A_i e^{j w_i t}) + n_u with
A_i = -w_i^2 X_i (Eq. 2), H from ``models``; white Gaussian noise n_x (m), n_u (V), seeded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from station.ident.models import Model
from station.ident.response.frf import FrequencyResponse, assemble, step_response

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SyntheticStep:
    """t (N,) in s, x (N,) in m, u (N,) in V, f_hz, radius_m."""

    t: FloatArray
    x: FloatArray
    u: FloatArray
    f_hz: float
    radius_m: float


def whole_period_samples(f_hz: float, fs_hz: float, min_duration_s: float) -> int:
    """Samples in the smallest whole number of periods lasting at least min_duration_s."""
    periods = int(np.ceil(min_duration_s * f_hz))
    return round(periods * fs_hz / f_hz)


def stepped_sine(model: Model, theta: ArrayLike, f_hz: ArrayLike, radius_m: ArrayLike, *, fs_hz: float,
                 duration_s: float, sigma_x_m: float, sigma_u_V: float, seed: int,
                 offset_V: float = -0.5, whole_periods: bool = True) -> list[SyntheticStep]:
    """One SyntheticStep per frequency (radius per step in m); noise from Generator(seed)."""
    rng = np.random.default_rng(seed)
    out = []
    t0 = 0.0
    for f, r in zip(np.atleast_1d(f_hz), np.atleast_1d(radius_m), strict=True):
        n = whole_period_samples(f, fs_hz, duration_s) if whole_periods else int(duration_s * fs_hz)
        t = t0 + np.arange(n) / fs_hz
        w = 2 * np.pi * f
        phi = rng.uniform(0, 2 * np.pi)
        X = r * np.exp(1j * (phi - np.pi / 2))  # r sin(wt + phi) = Re(X e^{jwt})
        H = model.response(theta, np.array([f]))[0]
        x = r * np.sin(w * t + phi) + rng.normal(0, sigma_x_m, n)
        u = offset_V + (H * (-(w**2)) * X * np.exp(1j * w * t)).real + rng.normal(0, sigma_u_V, n)
        out.append(SyntheticStep(t, x, u, float(f), float(r)))
        t0 = t[-1] + 1.0
    return out


def response_of(steps: list[SyntheticStep], n_harmonics: int = 3) -> FrequencyResponse:
    """H(f) of synthetic steps through the same sine fits as recordings."""
    return assemble([step_response(s.t, s.x, s.u, s.f_hz, n_harmonics=n_harmonics) for s in steps])
