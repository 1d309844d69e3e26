"""Per-step linear least-squares decomposition of both channels (the data side of the workflow).

Each step's record window (N samples, time tau from the window centre t_mid, h = T_window/2) is
decomposed on the basis

    force:        [lines outside the catalogue (nuisance)], [fundamental (cos, sin)], [harmonics
                  k = 2..K], [1, tau/h, (tau/h)^2], [mains lines]
    displacement: [fundamental], [1, tau/h, (tau/h)^2], [mains lines], [harmonics k = 2..K]

with k*f the crank harmonics and mains lines h*f_m (h = 1..H).  Lines the first pass finds in the
force residual outside this basis (``extra_hz``) are fitted too, first, so that the later rows of R
whiten the modelled coefficients *given* those lines (they do not leak into them); no model explains
them, so they stay in the gap and are reported as unexplained.  A sinusoid a cos(w tau) + b sin(w tau)
is stored as the phasor P = a - j b (signal = Re(P e^{j w tau})).  The fit is exact (QR), the residual
is orthogonal to the basis, and with B^T B = R^T R (Cholesky; R plays the role of QR's R):

    || y - B m ||^2 = || y - B c ||^2 + || R (c - m) ||^2     for any model coefficients m,

so every model's time-domain residual is evaluated from the coefficients c (shape (n_b,)) and R.
The noise standard deviation of each channel is estimated robustly from the residual periodogram
(median bin / ln 2, insensitive to lines the basis does not hold).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from station.discrepancy.spectrum import frequencies, hann
from station.errors import StationError
from station.ident.response.sinefit import unit_circle
from station.recording import Recording

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

K_MAX = 6  # crank harmonics per step (fundamental included)
MAINS_RANGE_HZ = (45.0, 65.0)
MAINS_H_MAX = 10
FLAT_TOP = 20  # samples: a run this long at the window extreme means a clipped channel


class FrequencyNotDetermined(StationError):
    """A window's sine fit cannot tell its frequency: the Gauss-Newton step's covariance gives the
    frequency no positive variance (the fundamental, its harmonics and the window's quadratic trend are
    not separable, as in a window of about one crank cycle)."""


@dataclass(frozen=True)
class StepWindow:
    """One step's record window: time origin t0_s (s, absolute time of its first sample), samples."""

    index: int
    f_nominal_hz: float
    t0_s: float
    displacement_m: FloatArray
    force_V: FloatArray


@dataclass(frozen=True)
class ChannelFit:
    """LS fit of one channel of one step on its basis.

    coef: (n_b,) coefficients; R: (n_b, n_b) upper-triangular factor of the basis; ssr: residual
    sum of squares (unit^2); sigma: robust noise standard deviation (unit); residual: (N,) samples.
    """

    coef: FloatArray
    R: FloatArray
    ssr: float
    sigma: float
    residual: FloatArray


@dataclass(frozen=True)
class StepDecomposition:
    """Both channels of one step decomposed.

    f_hz / f_std_hz: crank frequency fitted to the displacement (Hz); K: number of crank harmonics;
    t_mid_s: absolute time of the window centre; half_s: half the window length (poly scaling);
    mains_cols: per mains harmonic h (1..H) the crank harmonic k it coincides with (0 = own column);
    x1: displacement fundamental phasor (m) and x1_cov its (Re, Im) covariance (2, 2).
    """

    index: int
    f_hz: float
    f_std_hz: float
    K: int
    n_samples: int
    t_mid_s: float
    half_s: float
    mains_merge: tuple[int, ...]
    force: ChannelFit
    disp: ChannelFit
    x1: complex
    x1_cov: FloatArray
    flat_top: int = 0
    extra_hz: tuple[float, ...] = ()
    extra_amp: tuple[float, ...] = ()

    @property
    def n_extra(self) -> int:
        """Number of force basis columns of the nuisance lines (2 per line)."""
        return 2 * len(self.extra_hz)


def robust_sigma(residual: FloatArray) -> float:
    """Noise standard deviation from the median bin of the Hann-windowed periodogram (white Gaussian
    noise: the bins are exponential with mean sigma^2 sum(w^2), median ln 2 times that).  Lines, whose
    Hann leakage falls off as 1/k^3, do not bias it."""
    n = residual.size
    if n < 32:
        return float(np.std(residual))
    w, ww, _ = hann(n)
    spec = np.abs(np.fft.rfft(residual * w))[2:-1] ** 2
    return float(math.sqrt(np.median(spec) / (ww * math.log(2.0))))


def windows_of(rec: Recording) -> list[StepWindow]:
    """The usable steps' record windows; absolute time from the step document's ``t0_s`` when an
    import recorded it, else sample index / sample rate."""
    t0 = {}
    for doc in rec.documents:
        if doc.get("kind") == "step" and "t0_s" in doc and "index" in doc:
            t0[int(doc["index"])] = float(doc["t0_s"])
    out = []
    for s in rec.steps:
        if not s.usable:
            log.warning("step %d lost samples in its record window; left out", s.index)
            continue
        d, u = rec.step_signals(s)
        out.append(StepWindow(s.index, s.crank_frequency_hz, t0.get(s.index, s.start_sample / rec.sample_rate_hz),
                              d, u))
    return out


def harmonic_columns(tau: FloatArray, freqs_hz: list[float]) -> FloatArray:
    """Basis columns of m sine lines: (N, 2 m) array, cos then sin of each of the m frequencies
    ``freqs_hz`` (Hz) at the N times ``tau`` (s, (N,)); column 2 i is cos(2 pi f_i tau)."""
    w = 2 * np.pi * np.asarray(freqs_hz)
    arg = np.multiply.outer(tau, w)
    out = np.empty((tau.size, 2 * w.size))
    out[:, 0::2] = np.cos(arg)
    out[:, 1::2] = np.sin(arg)
    return out


def _harmonics_of(tau: FloatArray, f_hz: float, K: int, out: FloatArray | None = None) -> FloatArray:
    """Columns cos, sin (N, 2 K) of k f, k = 1..K, by powers of exp(j 2 pi f tau) (one complex
    exponential instead of K, itself a cosine and a sine: ``unit_circle``; rounding grows as k eps).
    ``out``: an (N, >= 2 K) array whose first 2 K columns receive them (and are returned), else a new
    array.  The powers are taken on whole contiguous rows of a (K, N) array, then written out in one
    transposing copy (the cos, sin pairs are the complex numbers' own layout)."""
    Z = np.empty((K, tau.size), dtype=np.complex128)
    z1 = Z[0]
    unit_circle(2 * np.pi * f_hz * tau, out=z1)
    for k in range(1, K):
        np.multiply(Z[k - 1], z1, out=Z[k])
    if out is None:
        return np.ascontiguousarray(Z.T).view(np.float64)
    cols = out[:, : 2 * K]
    cols.view(np.complex128)[...] = Z.T
    return cols


def coarse_frequency(x: FloatArray, fs: float, f_nominal: float) -> float:
    """Peak of the Hann-windowed, 8x zero-padded spectrum of x within +-20 % of f_nominal (Hz), refined
    by parabolic interpolation; f_nominal if the window holds too few periods to tell."""
    n = x.size
    spec = np.abs(np.fft.rfft((x - x.mean()) * hann(n)[0], 8 * n))
    fr = frequencies(8 * n, fs)
    band = np.nonzero((fr >= 0.8 * f_nominal) & (fr <= 1.2 * f_nominal))[0]
    if band.size < 3:
        return f_nominal
    i = int(band[np.argmax(spec[band])])
    if i in (band[0], band[-1]):
        return f_nominal
    a, b, c = np.log(spec[i - 1 : i + 2] + 1e-300)
    d = 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) < 0 else 0.0
    return float(fr[i] + d * (fr[1] - fr[0]))


def fit_frequency(tau: FloatArray, x: FloatArray, f0: float, K: int, extra: FloatArray | None = None,
                  iterations: int = 4) -> tuple[float, float]:
    """Four-parameter sine fit (IEEE 1057) of one channel with harmonics 2..K, a quadratic and the
    ``extra`` columns (N, m) (mains lines) as nuisance: returns (f, std f) in Hz, Gauss-Newton from f0.
    Raises ``FrequencyNotDetermined`` when the fit gives the frequency no positive variance."""
    f, std = f0, 0.0
    h = max(float(np.max(np.abs(tau))), 1e-12)
    n_x = 0 if extra is None else extra.shape[1]
    # J = [harmonics (2 K), 1, tau/h, (tau/h)^2, extra, d/df]: the nuisance columns written once, the
    # harmonics and the derivative again at each frequency; B (the basis) is J without its last column
    J = np.empty((tau.size, 2 * K + 3 + n_x + 1))
    J[:, 2 * K] = 1.0
    J[:, 2 * K + 1] = tau / h
    J[:, 2 * K + 2] = (tau / h) ** 2
    if extra is not None:
        J[:, 2 * K + 3 : -1] = extra
    B = J[:, :-1]
    a = b = None
    for _ in range(iterations):
        _harmonics_of(tau, f, K, out=J)
        if a is None or b is None:
            c = np.linalg.solve(B.T @ B, B.T @ x)
            a, b = c[0], c[1]
        J[:, -1] = tau * (-a * J[:, 1] + b * J[:, 0]) * 2 * np.pi
        JtJ = J.T @ J
        p = np.linalg.solve(JtJ, J.T @ x)
        r = x - J @ p
        s2 = float(r @ r) / max(x.size - J.shape[1], 1)
        cov = s2 * np.linalg.inv(JtJ)
        var = float(cov[-1, -1])
        if not var > 0.0:  # negative or NaN: JtJ is singular to working precision
            raise FrequencyNotDetermined(
                f"the sine fit cannot tell the frequency from the window's {x.size} samples "
                f"(its variance came out {var:.3g} Hz^2: the fundamental, {K - 1} harmonics and the trend are "
                "not separable)")
        f, std = f + float(p[-1]), math.sqrt(var)
        a, b = p[0], p[1]
        if abs(p[-1]) < 1e-2 * std:
            break
    return f, std


def fit_channel(B: FloatArray, y: FloatArray) -> ChannelFit:
    """Least-squares fit of one channel's N samples ``y`` (N,) (m or V) on the basis ``B`` (N, n_b), by
    the normal equations: B^T B = R^T R (R upper triangular), c = (B^T B)^-1 B^T y.  The returned
    :class:`ChannelFit` gives the residual of any other coefficients m without the samples:
    ||y - B m||^2 = ssr + ||R (c - m)||^2 (the model-gap fits rely on it)."""
    R = np.asarray(np.linalg.cholesky(B.T @ B).T, dtype=np.float64)
    c = np.asarray(np.linalg.solve(R, np.linalg.solve(R.T, B.T @ y)), dtype=np.float64)
    r = y - B @ c
    return ChannelFit(coef=c, R=R, ssr=float(r @ r), sigma=robust_sigma(r), residual=r)


def longest_flat_extreme(y: FloatArray) -> int:
    """Longest run of identical samples at the window's maximum or minimum (a clipped channel has
    long flat tops; a noisy unclipped one has runs of one or two)."""
    best = 0
    for v in (y.max(), y.min()):
        at = np.concatenate([[0], (y == v).astype(np.int8), [0]])
        d = np.diff(at)
        starts, ends = np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]
        if starts.size:
            best = max(best, int(np.max(ends - starts)))
    return best


def decompose_step(w: StepWindow, fs: float, f_mains: float | None, n_mains: int,
                   extra_hz: tuple[float, ...] = (), f_start: float | None = None) -> StepDecomposition:
    """Fit both channels of one step (see the module docstring for the basis); ``f_start``: the crank
    frequency of an earlier pass (Hz), refined by two Gauss-Newton steps with the new nuisance columns."""
    n = w.force_V.size
    tau = np.asarray((np.arange(n) - (n - 1) / 2) / fs, dtype=np.float64)
    half = n / (2 * fs)
    K = int(max(1, min(K_MAX, math.floor(0.45 * fs / w.f_nominal_hz))))
    merge, mains_f = [], []
    for hh in range(1, n_mains + 1):
        nu = hh * (f_mains or 0.0)
        k = round(nu / w.f_nominal_hz)
        if 1 <= k <= K and abs(nu - k * w.f_nominal_hz) < 0.5 / (2 * half):
            merge.append(k)
        else:
            merge.append(0)
            mains_f.append(nu)
    mains = harmonic_columns(tau, mains_f) if mains_f else np.zeros((n, 0))
    extra = harmonic_columns(tau, list(extra_hz)) if extra_hz else np.zeros((n, 0))
    nuisance = np.hstack([mains, extra])
    # the crank frequency is common to both channels: inverse-variance mean of the two 4-par fits,
    # started from the displacement's spectral peak within +-20 % of the nominal frequency
    it = 4 if f_start is None else 2
    f0 = coarse_frequency(w.displacement_m, fs, w.f_nominal_hz) if f_start is None else f_start
    fd, sd = fit_frequency(tau, w.displacement_m, f0, K, nuisance, it)
    fu, su = fit_frequency(tau, w.force_V, fd, K, nuisance, it)
    wd, wu = 1 / max(sd, 1e-300) ** 2, 1 / max(su, 1e-300) ** 2
    f, f_std = (wd * fd + wu * fu) / (wd + wu), 1 / math.sqrt(wd + wu)
    # force basis [extra, harmonics, 1, tau/h, (tau/h)^2, mains]; displacement basis [fundamental,
    # 1, tau/h, (tau/h)^2, mains, harmonics 2..K], each written column block by column block
    ne, nm = extra.shape[1], mains.shape[1]
    Bf = np.empty((n, ne + 2 * K + 3 + nm))
    Bf[:, :ne] = extra
    harm = _harmonics_of(tau, f, K, out=Bf[:, ne:])
    p0 = ne + 2 * K
    Bf[:, p0] = 1.0
    Bf[:, p0 + 1] = tau / half
    Bf[:, p0 + 2] = (tau / half) ** 2
    Bf[:, p0 + 3 :] = mains
    Bd = np.empty((n, 2 * K + 3 + nm))
    Bd[:, :2] = harm[:, :2]
    Bd[:, 2 : 5 + nm] = Bf[:, p0:]
    Bd[:, 5 + nm :] = harm[:, 2:]
    force = fit_channel(Bf, w.force_V)
    amp = tuple(float(np.hypot(force.coef[2 * j], force.coef[2 * j + 1])) for j in range(len(extra_hz)))
    disp = fit_channel(Bd, w.displacement_m)
    Rinv = np.linalg.inv(disp.R)
    cov = disp.sigma**2 * (Rinv @ Rinv.T)[:2, :2]
    T = np.array([[1.0, 0.0], [0.0, -1.0]])  # (a, b) -> (Re, Im) of a - j b
    return StepDecomposition(
        index=w.index, f_hz=f, f_std_hz=f_std, K=K, n_samples=n, t_mid_s=w.t0_s + (n - 1) / (2 * fs),
        half_s=half, mains_merge=tuple(merge), force=force, disp=disp,
        x1=complex(disp.coef[0], -disp.coef[1]), x1_cov=T @ cov @ T.T,
        flat_top=longest_flat_extreme(w.force_V), extra_hz=tuple(extra_hz), extra_amp=amp)


def basis_frequencies(s: StepDecomposition, f_mains: float | None) -> list[float]:
    """Frequencies (Hz) the step's basis holds: crank harmonics and mains lines."""
    out = [k * s.f_hz for k in range(1, s.K + 1)]
    out += [(h + 1) * (f_mains or 0.0) for h, k in enumerate(s.mains_merge) if k == 0]
    return out
