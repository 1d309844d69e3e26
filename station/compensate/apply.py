"""Apply a compensation filter to a measured signal, with the estimate's standard uncertainty at every
sample (GUM), in blocks with its state; and the Monte Carlo check (GUM Supplement 1).

For y[n] = sum_k b_k x[n-k] with uncertain coefficients b (covariance U_b) and a signal x whose noise
is stationary with autocovariance r (R its (taps, taps) Toeplitz matrix), GUM gives (Eichstädt,
Link, Elster, Sensors 10 (2010) 7621; Elster, Link, Metrologia 45 (2008) 464)

    u^2(y[n]) = x_n^T U_b x_n + b^T R b + tr(U_b R),     x_n = (x[n], x[n-1], ..., x[n-taps+1]).

The first term is a quadratic form over a sliding window.  With U_b = sum_i lambda_i v_i v_i^T
(eigenvalues below 1e-13 of the largest dropped: the design's U_b has the rank of the transducer's
parameter count) it is sum_i lambda_i (v_i * x)[n]^2: rank + 1 FIR sums per sample, fused with the
estimate's in one compiled pass (``kernel``; FFT convolutions beyond DIRECT_MAX_TAPS taps).  Before
the first sample the signal is taken as constant (x[-k] = x[0], its noise that of x[0]);
the first taps-1 outputs' noise term is computed for that exactly.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import toeplitz
from scipy.signal import oaconvolve

from station.compensate.design import CompensationFilter, coefficients_for
from station.errors import BadInputError

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

EIG_REL_TOL = 1e-13


@dataclass(frozen=True)
class Noise:
    """The signal's noise: one-sided autocovariance r[0], r[1], ... in unit_in^2 (stationary);
    white noise of standard deviation sigma is r = (sigma^2,)."""

    autocov: tuple[float, ...]

    @classmethod
    def white(cls, sigma: float) -> Noise:
        if not (math.isfinite(sigma) and sigma >= 0):
            raise BadInputError(f"noise standard deviation {sigma!r}: state a value >= 0")
        return cls((float(sigma) ** 2,))

    @classmethod
    def of(cls, autocov: ArrayLike) -> Noise:
        r = np.asarray(autocov, dtype=float).ravel()
        if r.size == 0 or not np.all(np.isfinite(r)) or r[0] < 0 or np.any(np.abs(r) > r[0] * (1 + 1e-12)):
            raise BadInputError("the noise autocovariance must be finite with |r[k]| <= r[0], r[0] >= 0")
        return cls(tuple(float(v) for v in r))

    def toeplitz(self, n: int) -> FloatArray:
        r = np.zeros(n)
        m = min(n, len(self.autocov))
        r[:m] = self.autocov[:m]
        return toeplitz(r)


DIRECT_MAX_TAPS = 256


def fir(x: FloatArray, w: FloatArray) -> FloatArray:
    """'valid' convolution of x (n + taps - 1,) with each row of w (r, taps) -> (r, n): direct up to
    DIRECT_MAX_TAPS taps (each output the same sum whatever the block), FFT overlap-add beyond."""
    if w.shape[1] <= DIRECT_MAX_TAPS:
        out = np.empty((w.shape[0], x.size - w.shape[1] + 1))
        for i, row in enumerate(w):
            out[i] = np.convolve(x, row, mode="valid")
        return out
    return oaconvolve(x[None, :], w, mode="valid", axes=1)


def _kernel() -> Callable[[FloatArray, FloatArray, float], tuple[FloatArray, FloatArray]] | None:
    """The compiled per-sample loop (``kernel``), or None without numba (numpy then convolves)."""
    try:
        from station.compensate.kernel import estimate_and_variance
    except ImportError as exc:  # pragma: no cover - numba is a dependency
        log.warning("compensation runs in numpy (slower): numba is unavailable: %s", exc)
        return None
    return estimate_and_variance


def estimate_and_variance(xe: FloatArray, w: FloatArray, var0: float) -> tuple[FloatArray, FloatArray]:
    """y = w_0 * x and var = var0 + sum_{i>=1} (w_i * x)^2 ('valid', (n,) each) for xe (n + taps - 1,)
    and w (1 + r, taps): the compiled loop up to DIRECT_MAX_TAPS taps, FFT convolutions beyond."""
    kern = _kernel() if w.shape[1] <= DIRECT_MAX_TAPS else None
    if kern is not None:
        return kern(xe, np.ascontiguousarray(w[:, ::-1]), float(var0))
    Z = fir(xe, w)
    return Z[0], np.sum(Z[1:] ** 2, axis=0) + var0


class Compensator:
    """Streaming compensation: ``process(block)`` returns the estimate and its standard uncertainty
    for the block's samples (unit_out), keeping the last taps-1 samples as state; blocks of any size
    give the numbers of one pass."""

    def __init__(self, filt: CompensationFilter, noise: Noise) -> None:
        self.filt = filt
        self.noise = noise
        self.b = b = filt.b_array
        self.U = U = filt.b_cov_array  # (taps, taps), converted once: the filter keeps tuples
        self.N = N = b.size
        w, V = np.linalg.eigh(U)
        keep = w > EIG_REL_TOL * max(float(w.max()), 0.0) if w.max() > 0 else np.zeros(w.size, bool)
        self.W = np.vstack([b[None, :], (V[:, keep] * np.sqrt(w[keep])).T])  # (1 + r, N)
        R = noise.toeplitz(N)
        self.var_noise = float(b @ R @ b + np.sum(U * R))
        self._tail: FloatArray | None = None
        self.samples = 0

    def _start_noise(self, n: int) -> FloatArray:
        """Noise terms of outputs 0..n-1 (n < taps) with the signal constant before its first sample:
        output j sees x[j], ..., x[1] through b_0..b_{j-1} and x[0] through sum_{k>=j} b_k."""
        b, U = self.b, self.U
        r = self.noise.autocov
        if len(r) == 1 or not any(r[1:]):  # white: closed form with cumulative sums
            jj = np.arange(n)
            head_b = np.concatenate([[0.0], np.cumsum(b**2)])[jj]
            tail_b = np.cumsum(b[::-1])[::-1][jj]
            head_u = np.concatenate([[0.0], np.cumsum(np.diag(U))])[jj]
            S = np.cumsum(np.cumsum(U[::-1, ::-1], axis=0), axis=1)[::-1, ::-1]  # S[j, j] = sum_{k,l>=j} U_kl
            return r[0] * (head_b + tail_b**2 + head_u + np.diag(S)[jj])
        out = np.empty(n)
        for j in range(n):
            M = np.zeros((self.N, j + 1))  # window (x[j], ..., x[0], x[0], ...) from (x[j], ..., x[0])
            M[: j + 1, : j + 1] = np.eye(j + 1)
            M[j + 1:, j] = 1.0
            Rw = M @ self.noise.toeplitz(j + 1) @ M.T
            out[j] = b @ Rw @ b + np.sum(U * Rw)
        return out

    def process(self, block: ArrayLike) -> tuple[FloatArray, FloatArray]:
        x = np.asarray(block, dtype=float).ravel()
        if x.size == 0:
            return np.empty(0), np.empty(0)
        if not np.all(np.isfinite(x)):
            bad = int(np.flatnonzero(~np.isfinite(x))[0])
            raise BadInputError(f"the signal is not finite at sample {self.samples + bad} "
                                f"({int(np.sum(~np.isfinite(x)))} such samples in this block): nothing was compensated")
        tail = np.full(self.N - 1, x[0]) if self._tail is None else self._tail
        xe = np.concatenate([tail, x])
        with np.errstate(over="ignore", invalid="ignore"):  # an overflow is refused below
            y, var = estimate_and_variance(xe, self.W, self.var_noise)
        if self.samples < self.N - 1:
            n0 = min(self.N - 1 - self.samples, x.size)
            var[:n0] += self._start_noise(self.samples + n0)[self.samples:] - self.var_noise
        if not (np.all(np.isfinite(y)) and np.all(np.isfinite(var))):
            raise BadInputError(f"the signal's magnitude overflows the compensation near sample {self.samples}: "
                                "rescale it (state it in a smaller unit)")
        self._tail = xe[xe.size - (self.N - 1):] if self.N > 1 else np.empty(0)
        self.samples += x.size
        return y, np.sqrt(np.maximum(var, 0.0, out=var), out=var)


def compensate(filt: CompensationFilter, x: ArrayLike, noise: Noise,
               block: int = 1 << 16) -> tuple[FloatArray, FloatArray]:
    """The whole signal in blocks of ``block`` samples: estimate and standard uncertainty (n,)."""
    comp = Compensator(filt, noise)
    return collect(comp.process(b) for b in blocks(np.asarray(x, dtype=float), block))


def blocks(x: FloatArray, size: int) -> Iterator[FloatArray]:
    for i in range(0, x.size, size):
        yield x[i:i + size]


def collect(parts: Iterable[tuple[FloatArray, FloatArray]]) -> tuple[FloatArray, FloatArray]:
    ys, us = [], []
    for y, u in parts:
        ys.append(y)
        us.append(u)
    return (np.concatenate(ys), np.concatenate(us)) if ys else (np.empty(0), np.empty(0))


def _noise_draws(noise: Noise, n: int, m: int, rng: np.random.Generator) -> FloatArray:
    """m draws of n samples of the stationary noise (m, n): white directly, coloured by circulant
    embedding (refused when the embedding is not positive semi-definite)."""
    r = np.asarray(noise.autocov)
    if r.size == 1 or not np.any(r[1:]):
        return rng.standard_normal((m, n)) * math.sqrt(r[0])
    L = max(n, r.size)
    c = np.zeros(2 * L)
    c[: min(r.size, L)] = r[:L]
    c[2 * L - min(r.size, L) + 1:] = r[1:min(r.size, L)][::-1]
    lam = np.fft.fft(c).real
    if lam.min() < -1e-10 * lam.max():
        raise BadInputError("the noise autocovariance cannot be simulated (its circulant embedding is not "
                            "positive semi-definite): the Monte Carlo check needs another autocovariance")
    z = rng.standard_normal((m, 2 * L)) + 1j * rng.standard_normal((m, 2 * L))
    e = np.fft.fft(z * np.sqrt(np.clip(lam, 0, None) / (2 * L)), axis=1).real
    return e[:, :n]


def monte_carlo(filt: CompensationFilter, x: ArrayLike, noise: Noise, draws: int, seed: int = 0,
                chunk: int = 500) -> tuple[FloatArray, FloatArray]:
    """GUM-S1: ``draws`` draws of the transducer's parameters (normal, the design's covariance) and
    of the noise; each draw's filter is redesigned (``coefficients_for``) and applied to the signal
    plus that noise.  Returns the mean and standard deviation of the estimates (n,)."""
    if not (1 <= draws <= 1_000_000):
        raise BadInputError(f"--monte-carlo {draws}: choose 1 to 1000000 draws")
    xs = np.asarray(x, dtype=float)
    rng = np.random.default_rng(seed)
    s = filt.sensor
    w, V = np.linalg.eigh(s.cov_array)
    A = V * np.sqrt(np.clip(w, 0, None))
    N = len(filt.b)
    mean = np.zeros(xs.size)
    m2 = np.zeros(xs.size)
    done = 0
    while done < draws:
        m = min(chunk, draws - done)
        th = s.theta_array + rng.standard_normal((m, s.theta_array.size)) @ A.T
        B = coefficients_for(filt, th)
        xn = xs[None, :] + _noise_draws(noise, xs.size, m, rng)
        xe = np.concatenate([np.repeat(xn[:, :1], N - 1, axis=1), xn], axis=1)
        Y = oaconvolve(xe, B, mode="valid", axes=1)
        # Chan's parallel update of mean and sum of squared deviations
        cm = Y.mean(axis=0)
        cM2 = ((Y - cm) ** 2).sum(axis=0)
        delta = cm - mean
        tot = done + m
        mean = mean + delta * m / tot
        m2 = m2 + cM2 + delta**2 * done * m / tot
        done = tot
    return mean, np.sqrt(m2 / max(done - 1, 1))
