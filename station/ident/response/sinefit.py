"""Least-squares sine fits (IEEE 1057 three- and four-parameter, ISO 16063-11 style).

Model of one channel over one step, t in s measured from the window centre t_c:

    x(t) = Re(X e^{j w t}) + C + sum_{h=2..n_h} Re(X_h e^{j h w t}),   X = A - jB

i.e. x = A cos(w t) + B sin(w t) + C (+ harmonics, which the crank mechanism produces and which
are orthogonal nuisance terms).

Quantisation (``quantisation_cov``).  A channel recorded as converter counts sits on a grid of step
q.  Noise of standard deviation sigma well above q (>= 0.85 q) dithers the grid: the quantisation
error is white and ``s^2`` covers it.  Below that its mean given the signal, the noise-averaged
sawtooth g(x) = (q/pi) sum_k (-1)^k/k exp(-2 pi^2 k^2 sigma^2/q^2) sin(2 pi k x/q), is a function of
the signal: periodic with the sine, so part of it lands on the fundamental as a phasor error the
white formula misses (at 245 codes amplitude and sigma = 0.33 q, 200 samples a period: the phasor's
variance 2.4 times the white one).  Its value depends on where the samples fall on the grid (the
phase, the offset), so it is stated as a covariance: the mean square of that phasor error over
phases, in the frame of the fitted phasor, computed on whole periods of at most about 8192 samples
(the pattern repeats with the sine: the same per period where the period is a whole number of
samples, an upper estimate otherwise).  Three-parameter fit: w known, linear LS.  Four-parameter fit:
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


def unit_circle(phase: FloatArray, out: NDArray[np.complex128] | None = None) -> NDArray[np.complex128]:
    """exp(j phase) for real phases (rad, shape (N,)) as cos(phase) + j sin(phase), written into ``out``
    (complex, (N,)) when given: the numbers of ``np.exp(1j * phase)`` (whose real part is 0 here, so it
    is the cosine and the sine of the imaginary part) at a third of its cost."""
    z = np.empty(phase.shape, dtype=np.complex128) if out is None else out
    np.cos(phase, out=z.real)
    np.sin(phase, out=z.imag)
    return z


def design(t: FloatArray, w: float, n_harmonics: int, extra: int = 0) -> FloatArray:
    """Columns cos(w t), sin(w t), 1, then cos/sin of the harmonics 2..n_h; shape (N, 1 + 2 n_h)
    (``extra`` more columns after them, left for the caller to fill).  The harmonics' powers of
    exp(j w t) are taken on contiguous rows and written as complex numbers (a cos, sin pair is a
    complex number's layout)."""
    J = np.empty((t.size, 1 + 2 * n_harmonics + extra))
    e = unit_circle(w * t)
    J[:, 0:2].view(np.complex128)[:, 0] = e
    J[:, 2] = 1.0
    if n_harmonics > 1:
        E = np.empty((n_harmonics - 1, t.size), dtype=np.complex128)
        np.multiply(e, e, out=E[0])
        for h in range(1, n_harmonics - 1):
            np.multiply(E[h - 1], e, out=E[h])
        J[:, 3 : 1 + 2 * n_harmonics].view(np.complex128)[...] = E.T
    return J


def _solve(J: FloatArray, y: FloatArray) -> FloatArray:
    """Least squares by the normal equations (columns are near-orthogonal sines: well conditioned)."""
    return np.asarray(np.linalg.solve(J.T @ J, J.T @ y), dtype=np.float64)


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
    J = design(t - tc, 2 * np.pi * f_hz, n_harmonics)
    p = _solve(J, y)
    return _finish(y, J, p, f_hz, 0.0, tc, n_harmonics=n_harmonics)


def _dw(t: FloatArray, J0: FloatArray, p: FloatArray, n_harmonics: int, out: FloatArray | None = None
        ) -> FloatArray:
    """d(model)/dw for the design J0 and coefficients p (A cos + B sin per harmonic h); written into
    ``out`` (N,) when given."""
    d: FloatArray = t * (-p[0] * J0[:, 1] + p[1] * J0[:, 0])
    for h in range(2, n_harmonics + 1):
        a, b = p[2 * h - 1], p[2 * h]
        d += h * t * (-a * J0[:, 2 * h] + b * J0[:, 2 * h - 1])
    if out is not None:
        out[...] = d
        return out
    return d


def estimate_frequency(t: FloatArray, y: FloatArray, f0_hz: float, *, t_center_s: float | None = None,
                       n_harmonics: int = 1, max_iter: int = 20) -> tuple[float, float, float]:
    """Frequency by the four-parameter fit (IEEE 1057 4.1.3.3): Gauss-Newton on (A, B, C,
    [harmonics], w) from a three-parameter fit at f0_hz, first on a subsample (>= 2000 points),
    then one step on all samples.  Returns (f_hz, f_std_hz, t_center_s)."""
    t = np.asarray(t, float)
    y = np.asarray(y, float)
    tc = float(np.mean(t)) if t_center_s is None else t_center_s
    tt = t - tc
    w = 2 * np.pi * f0_hz
    stride = max(1, tt.size // 2000)
    p = _solve(design(tt[::stride], w, n_harmonics), y[::stride])
    f_std = 0.0
    for sl, n_it in ((slice(None, None, stride), max_iter), (slice(None), 1)):
        ts, ys = tt[sl], y[sl]
        for _ in range(n_it):
            J = design(ts, w, n_harmonics, extra=1)  # [J0, d/dw]
            J0 = J[:, :-1]
            _dw(ts, J0, p, n_harmonics, out=J[:, -1])
            JtJ = J.T @ J
            r = ys - J0 @ p
            step = np.linalg.solve(JtJ, J.T @ r)
            p = p + step[:-1]
            w += step[-1]
            s2 = float(r @ r) / max(ys.size - J.shape[1], 1)
            f_std = float(np.sqrt(np.linalg.inv(JtJ)[-1, -1] * s2)) / (2 * np.pi)
            if abs(step[-1]) < 1e-12 * w:
                break
    return w / (2 * np.pi), f_std, tc


def fit_channels(t: FloatArray, Y: FloatArray, f_hz: float, *, t_center_s: float,
                 n_harmonics: int = 1) -> list[SineFit]:
    """Three-parameter fits of several channels (columns of Y, shape (N, n_ch)) at one frequency
    and time origin, sharing the design matrix."""
    t = np.asarray(t, float)
    J = design(t - t_center_s, 2 * np.pi * f_hz, n_harmonics)
    JtJ = J.T @ J
    P = np.asarray(np.linalg.solve(JtJ, J.T @ Y), dtype=np.float64)
    Ji = np.asarray(np.linalg.inv(JtJ), dtype=np.float64)
    return [_finish(Y[:, c], J, P[:, c], f_hz, 0.0, t_center_s, cov_extra=Ji, n_harmonics=n_harmonics)
            for c in range(Y.shape[1])]


QUANT_PHASES = 16  # phases over which the quantisation error of the phasor is averaged
QUANT_SAMPLES = 8192  # at most this many samples (whole periods) carry the computation
_QUANT_RNG_SEED = 20_000  # fixed phases: never commensurate with a sampling period


def quantisation_step(y: FloatArray) -> tuple[float, float] | None:
    """(q, origin) when the samples y (N,) sit on a grid origin + k q (a channel stored as converter
    counts times a scale), else None (float data, resampled or filtered).  q: the smallest nonzero
    step between consecutive samples."""
    d = np.abs(np.diff(y))
    d = d[d > 0]
    if d.size == 0:
        return None
    q = float(d.min())
    k = (y - y[0]) / q
    if float(np.max(np.abs(k - np.round(k)))) > 1e-3:
        return None
    return q, float(y[0])


def quantisation_cov(t: FloatArray, y: FloatArray, fit: SineFit, n_harmonics: int = 1) -> FloatArray:
    """Covariance (2, 2) of (Re X, Im X) the quantisation of y adds to a sine fit's phasor
    (module docstring); zeros when y is not on a grid or its noise dithers the grid.

    t: sample times in s (N,); y: samples (N,) in the channel's unit; fit: the sine fit of y."""
    grid = quantisation_step(y)
    out = np.zeros((2, 2))
    if grid is None or abs(fit.phasor) == 0:
        return out
    q, origin = grid
    n_eff = max(fit.n_samples - (1 + 2 * n_harmonics), 1)
    sigma2 = max(fit.residual_rms**2 * fit.n_samples / n_eff - q * q / 12, (0.05 * q) ** 2)
    k = np.arange(1, 21)
    a = np.exp(-2 * np.pi**2 * k**2 * sigma2 / q**2)
    k, a = k[a > 1e-6], a[a > 1e-6]
    if k.size == 0:
        return out
    w = 2 * np.pi * fit.frequency_hz
    tt = np.asarray(t, float)
    if tt.size > QUANT_SAMPLES:  # whole periods: the error's mean square per period, as over the window
        per = 2 * np.pi / (w * float(np.median(np.diff(tt[:100]))))  # samples per period
        tt = tt[:min(tt.size, int(np.ceil(np.ceil(QUANT_SAMPLES / per) * per)))]
    tt = tt - float(np.mean(tt))
    J = design(tt, w, n_harmonics)
    proj = np.linalg.inv(J.T @ J)[:2] @ J.T  # (2, N): coefficients A, B of the fundamental
    phases = np.random.default_rng(_QUANT_RNG_SEED).uniform(0.0, 2 * np.pi, QUANT_PHASES)
    # cos(w t + phase) = cos(w t) cos(phase) - sin(w t) sin(phase): 2 N cosines (the design's first two
    # columns, cos(w t) and sin(w t)), not N P
    x = np.outer(J[:, 0], abs(fit.phasor) * np.cos(phases))  # (N, P), in units of q below
    x -= np.outer(J[:, 1], abs(fit.phasor) * np.sin(phases))
    x += fit.offset - origin
    x *= 1.0 / q
    g = _periodic_sine_series(x, (-1.0) ** k / k * a)
    AB = np.einsum("in,np->ip", proj, g) * (q / np.pi)  # (2, P); a tall BLAS product spins its threads
    b = (AB[0] - 1j * AB[1]) * np.exp(-1j * phases) * np.exp(1j * np.angle(fit.phasor))  # X = A - jB
    return np.array([[np.mean(b.real**2), np.mean(b.real * b.imag)],
                     [np.mean(b.real * b.imag), np.mean(b.imag**2)]])


_SERIES_GRID = 1 << 15  # points per period of the tabulated series: linear interpolation within 1e-6 of it


def _periodic_sine_series(cycles: FloatArray, c: FloatArray) -> FloatArray:
    """sum_k c[k-1] sin(2 pi k cycles) for k = 1..len(c), elementwise, tabulated over one period and
    interpolated linearly: at most 20 harmonics of coefficients |c_k| <= 1/k on a grid of 2^15 points
    per period are within (2 pi/2^15)^2/8 sum k (below 4e-7) of the series, for a few hundred thousand
    points a fraction of its direct cost.
    The table is one inverse real FFT (its bin k holds -j c_k M/2); the grid cell of a point is its
    integer part modulo 2^15 taken as bits, so the phase is never reduced by a floating modulo.
    cycles is overwritten (any shape; the result has its shape)."""
    m = _SERIES_GRID
    spectrum = np.zeros(m // 2 + 1, dtype=complex)
    spectrum[1:c.size + 1] = -0.5j * m * np.asarray(c, float)
    table = np.fft.irfft(spectrum, m)  # table[i] = sum_k c_k sin(2 pi k i / m)
    slope = np.roll(table, -1) - table  # per cell, the last wrapping to the first
    u = np.multiply(cycles, m, out=cycles)  # grid units
    cell = np.floor(u)
    u -= cell  # the fraction of the cell
    i = cell.astype(np.int64)
    i &= m - 1  # modulo 2^15, also for negative cells (two's complement)
    out: FloatArray = table[i]
    out += u * slope[i]
    return out


def with_quantisation(t: FloatArray, y: FloatArray, fit: SineFit, n_harmonics: int = 1) -> SineFit:
    """fit with ``quantisation_cov`` added to its phasor covariance."""
    cq = quantisation_cov(t, y, fit, n_harmonics)
    if not cq.any():
        return fit
    return SineFit(fit.frequency_hz, fit.frequency_std_hz, fit.phasor, fit.phasor_cov + cq, fit.offset,
                   fit.offset_std, fit.residual_rms, fit.n_samples, fit.t_center_s, fit.harmonics)


def fit4(t: FloatArray, y: FloatArray, f0_hz: float, *, t_center_s: float | None = None,
         n_harmonics: int = 1, max_iter: int = 20) -> SineFit:
    """Four-parameter sine fit (IEEE 1057 4.1.3.3): ``estimate_frequency`` then the three-parameter
    fit at that frequency (phasor covariance conditional on the frequency; with the time origin at
    the window centre the two are uncorrelated to first order)."""
    f, f_std, tc = estimate_frequency(t, y, f0_hz, t_center_s=t_center_s, n_harmonics=n_harmonics,
                                      max_iter=max_iter)
    fit = fit3(t, y, f, t_center_s=tc, n_harmonics=n_harmonics)
    return SineFit(f, f_std, fit.phasor, fit.phasor_cov, fit.offset, fit.offset_std, fit.residual_rms,
                   fit.n_samples, tc, fit.harmonics)
