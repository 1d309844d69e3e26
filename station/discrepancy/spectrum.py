"""Line search in the residual spectra: mains detection and the structure the basis does not hold.

Normalised Hann-windowed periodogram of a residual r (N samples, robust noise sigma, window w):
P(nu) = |sum w r e^{-j 2 pi nu t}|^2 / (sigma^2 sum w^2), computed with zero padding (``PAD``-fold) so
that lines between bins are not missed.  For white Gaussian noise P is exponentially distributed with
mean 1 at each frequency, so a line is significant when P exceeds -ln(alpha / n_bins); a sinusoid of
amplitude A gives |sum w r e| = A sum(w) / 2, i.e. A = 2 sqrt(P sigma^2 sum w^2) / sum w (V or m).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.special import gammainccinv  # scipy.stats.gamma.isf without importing scipy.stats

FloatArray = NDArray[np.float64]
PAD = 8


@dataclass(frozen=True)
class Line:
    """A significant line in one step's residual: frequency (Hz), amplitude (channel unit), P."""

    step: int
    frequency_hz: float
    amplitude: float
    power: float


@functools.lru_cache(maxsize=16)
def hann(n: int) -> tuple[FloatArray, float, float]:
    """The Hann window of n samples (``np.hanning``; read-only, shape (n,)), its energy w @ w and its
    sum w.sum(), kept per length: a recording's windows have one or a few lengths and every residual's
    periodogram and line amplitude uses them."""
    w = np.hanning(n)
    w.flags.writeable = False
    return w, float(w @ w), float(w.sum())


@functools.lru_cache(maxsize=16)
def frequencies(m: int, fs: float) -> FloatArray:
    """``np.fft.rfftfreq(m, 1 / fs)`` (Hz, shape (m // 2 + 1,)), read-only, kept per (m, fs)."""
    fr = np.asarray(np.fft.rfftfreq(m, 1.0 / fs), dtype=np.float64)
    fr.flags.writeable = False
    return fr


def normalised_periodogram(r: FloatArray, sigma: float, fs: float) -> tuple[FloatArray, FloatArray]:
    """(frequencies in Hz, P) of residual r with zero padding; P has mean 1 for white noise.  The
    frequencies (shape (PAD N / 2 + 1,)) are shared between calls: read-only."""
    n = r.size
    w, ww, _ = hann(n)
    spec = np.abs(np.fft.rfft(r * w, PAD * n)) ** 2 / (ww * max(sigma, 1e-300) ** 2)
    return frequencies(PAD * n, fs), spec


def line_amplitude(P: float, sigma: float, n: int) -> float:
    """Amplitude of a sinusoid whose normalised Hann periodogram value is P (channel unit)."""
    _, ww, wsum = hann(n)
    return float(2.0 * math.sqrt(P * sigma**2 * ww) / wsum)


def mains_statistic(residuals: list[FloatArray], sigmas: list[float], fs: float,
                    f_range: tuple[float, float], harmonics: int = 3,
                    spectra: list[tuple[FloatArray, FloatArray]] | None = None
                    ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per-step harmonic-sum statistic on a 0.01 Hz grid over ``f_range``: S_i(nu) = sum_h P_i(h nu).

    Returns (grid (G,), summed over steps (G,), per step (n_steps, G))."""
    grid = np.arange(f_range[0], f_range[1], 0.01)
    per = np.zeros((len(residuals), grid.size))
    for i, (r, s) in enumerate(zip(residuals, sigmas, strict=True)):
        fr, P = spectra[i] if spectra else normalised_periodogram(r, s, fs)
        for h in range(1, harmonics + 1):
            if h * grid[-1] < fr[-1]:
                per[i] += np.interp(h * grid, fr, P)
    return grid, per.sum(axis=0), per


MAINS_NOMINAL_HZ = (50.0, 60.0)
MAINS_TOL = 0.02  # a mains line is within 2 % of its nominal frequency (``physical``)


@dataclass(frozen=True)
class MainsDetection:
    """Mains line search: frequency (Hz) or None, number of harmonics to model, evidence text."""

    frequency_hz: float | None
    harmonics: int
    evidence: str


def detect_mains(residuals: list[FloatArray], sigmas: list[float], fs: float,
                 f_range: tuple[float, float], h_max: int, alpha: float = 1e-6,
                 spectra: list[tuple[FloatArray, FloatArray]] | None = None) -> MainsDetection:
    """Find a line common to the steps in ``f_range`` (with harmonics); it must stand out in the
    sum over steps (Gamma test at ``alpha`` after the number of grid cells searched) *and* in at least
    half of the steps (a line of one step only is not mains).  Mains is at a mains frequency: only
    ``MAINS_TOL`` around 50 and 60 Hz is searched, and the line's own fundamental must be significant
    (alpha 1e-4): a line that is only a "harmonic" of a grid frequency (the transducer's own free
    oscillation, say) is not mains.  Harmonics up to ``h_max`` are kept when each is significant
    (alpha 1e-4) in the summed single-harmonic power.  ``spectra``: the residuals'
    ``normalised_periodogram`` when the caller has them already."""
    n = len(residuals)
    if n == 0:
        return MainsDetection(None, 0, "no steps")
    if spectra is None:
        spectra = [normalised_periodogram(r, s, fs) for r, s in zip(residuals, sigmas, strict=True)]
    grid, total, per = mains_statistic(residuals, sigmas, fs, f_range, spectra=spectra)
    at_mains = np.zeros(grid.size, bool)
    for f0 in MAINS_NOMINAL_HZ:
        at_mains |= np.abs(grid / f0 - 1) <= MAINS_TOL
    if not np.any(at_mains):
        return MainsDetection(None, 0, f"no mains frequency in {f_range[0]:g}-{f_range[1]:g} Hz")
    total = np.where(at_mains, total, -np.inf)
    j = int(np.argmax(total))
    width = float(np.count_nonzero(at_mains)) * float(grid[1] - grid[0] if grid.size > 1 else 0.01)
    trials = width * max(r.size for r in residuals) / fs  # independent cells
    thresh = gammainccinv(3 * n, alpha / max(trials, 1.0))
    per_step = gammainccinv(3, 1e-3)
    steps_with = int(np.count_nonzero(per[:, j] > per_step))
    if total[j] < thresh or steps_with < math.ceil(n / 2):
        return MainsDetection(None, 0, f"no line common to the steps in {f_range[0]:g}-{f_range[1]:g} Hz "
                                       f"(max statistic {total[j]:.3g} at {grid[j]:.2f} Hz, threshold "
                                       f"{thresh:.3g}, in {steps_with}/{n} steps)")
    f_m = float(grid[j])
    p1 = sum(float(np.interp(f_m, fr, P)) for fr, P in spectra)
    if p1 < gammainccinv(n, 1e-4):
        return MainsDetection(None, 0, f"lines at harmonics of {f_m:.2f} Hz but none at {f_m:.2f} Hz itself: "
                                       "not mains (e.g. the transducer's own free oscillation)")
    keep = 1
    t1 = gammainccinv(n, 1e-4)
    for h in range(2, h_max + 1):
        p = 0.0
        for fr, P in spectra:
            if h * f_m < 0.45 * fs:
                p += float(np.interp(h * f_m, fr, P))
        if p > t1:
            keep = h
    return MainsDetection(f_m, keep, f"line at {f_m:.2f} Hz in {steps_with}/{n} steps "
                                     f"(statistic {total[j]:.3g} > {thresh:.3g}), harmonics up to {keep}")


def significant_lines(r: FloatArray, sigma: float, fs: float, step: int, alpha: float = 1e-4,
                      f_max: float | None = None, *, spectrum: tuple[FloatArray, FloatArray] | None = None
                      ) -> list[Line]:
    """Local maxima of the normalised periodogram above -ln(alpha / n_bins) (bins of 1/T), i.e. lines
    the basis does not hold.  Returns them sorted by power, strongest first (at most 20).
    ``spectrum``: ``normalised_periodogram(r, sigma, fs)`` when the caller has it already."""
    fr, P = normalised_periodogram(r, sigma, fs) if spectrum is None else spectrum
    n_bins = r.size / 2
    thr = -math.log(alpha / n_bins)
    top = f_max if f_max is not None else 0.45 * fs
    idx = np.nonzero((P[1:-1] > thr) & (P[1:-1] >= P[:-2]) & (P[1:-1] >= P[2:]) & (fr[1:-1] <= top))[0] + 1
    lines = []
    for i in idx:
        # parabolic interpolation of log P around the peak bin (Hann main lobe is nearly Gaussian)
        a, b, c = (math.log(max(float(P[j]), 1e-300)) for j in (i - 1, i, i + 1))
        d = 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) < 0 else 0.0
        peak = math.exp(b - 0.25 * (a - c) * d)
        lines.append(Line(step, float(fr[i] + d * (fr[1] - fr[0])), line_amplitude(peak, sigma, r.size), peak))
    # side lobes of a strong line are local maxima too: drop weak peaks close to a stronger line
    lines.sort(key=lambda ln: -ln.power)
    kept: list[Line] = []
    res = fs / r.size
    for ln in lines:
        if all(abs(ln.frequency_hz - k.frequency_hz) > 4 * res or ln.power > 1e-2 * k.power for k in kept):
            kept.append(ln)
        if len(kept) >= 20:
            break
    return kept
