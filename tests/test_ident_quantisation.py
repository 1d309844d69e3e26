"""A sine fit's phasor covariance covers the quantisation error its noise does not dither.

Truth from a direct construction (a sine at a known phasor, Gaussian noise, an ideal rounding
converter), not from the code under test: the fitted phasor's error, whitened by the stated
covariance, must have unit mean square over seeded random phases (the phase a daemon run's step
happens to start at).
"""

from __future__ import annotations

import numpy as np
import pytest

from station.ident.response.sinefit import fit3, quantisation_cov, quantisation_step, with_quantisation

FS = 20_000.0
LSB = 20.0 / 2**16  # a 16-bit converter over +-10 V


def _trials(f_hz: float, amp_V: float, noise_V: float, n: int, seed: int,
            offset_V: float = 0.0, n_samples: int = 4000) -> tuple[float, float]:
    """Mean square of the whitened phasor error over n random phases: (white covariance only, with
    the quantisation term)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_samples) / FS
    tc = float(t.mean())
    z_white: list[float] = []
    z_q: list[float] = []
    for _ in range(n):
        ph = rng.uniform(0, 2 * np.pi)
        v = amp_V * np.cos(2 * np.pi * f_hz * t + ph) + offset_V + noise_V * rng.standard_normal(t.size)
        y = np.round(v / LSB) * LSB
        fit = fit3(t, y, f_hz, n_harmonics=3)
        truth = amp_V * np.exp(1j * (ph + 2 * np.pi * f_hz * tc))
        e = np.array([(fit.phasor - truth).real, (fit.phasor - truth).imag])
        for cov, out in ((fit.phasor_cov, z_white), (with_quantisation(t, y, fit, 3).phasor_cov, z_q)):
            w = np.linalg.inv(np.linalg.cholesky(cov)) @ e
            out.append(float(w @ w) / 2)
    return float(np.mean(z_white)), float(np.mean(z_q))


def test_undithered_quantisation_is_in_the_phasor_covariance() -> None:
    """245 codes amplitude at 100 Hz, noise 0.33 code, 2 s (the simulated rig's displacement channel
    at its 100 Hz step): the white formula understates the phasor's variance about 2.5-fold (the
    quantisation error is periodic with the sine, 200 samples a period); with the quantisation term
    the whitened error has unit mean square (16 phases: 32 squares, std 0.25)."""
    white, with_q = _trials(100.0, 245 * LSB, 0.33 * LSB, 16, seed=11, n_samples=40_000)
    assert white > 1.8, white
    assert 0.6 < with_q < 1.5, with_q


def test_dithered_or_float_channels_are_left_alone() -> None:
    """Noise of 1.6 codes dithers the grid (the force channel): nothing added, and the white
    covariance is already right; data off any grid (float, filtered) get nothing either."""
    white, with_q = _trials(100.0, 1000 * LSB, 1.6 * LSB, 20, seed=12)
    assert white == with_q
    assert 0.5 < white < 1.6
    t = np.arange(2000) / FS
    y = 0.1 * np.sin(2 * np.pi * 50 * t) + 1e-5 * np.random.default_rng(3).standard_normal(t.size)
    assert quantisation_step(y) is None
    assert not quantisation_cov(t, y, fit3(t, y, 50.0)).any()


@pytest.mark.parametrize("origin", [0.0, 0.37 * LSB])
def test_grid_step_and_origin_are_found(origin: float) -> None:
    t = np.arange(2000) / FS
    y = np.round(0.05 * np.sin(2 * np.pi * 50 * t) / LSB) * LSB + origin
    q, o = quantisation_step(y)  # type: ignore[misc]
    assert q == pytest.approx(LSB, rel=1e-9)
    assert (o - origin) / LSB == pytest.approx(round((o - origin) / LSB), abs=1e-6)
