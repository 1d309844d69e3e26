"""Least-squares FIR inverse filter of a transducer, with a regularising low-pass and a delay, and its
coefficients' covariance propagated from the transducer's (Eichstädt, Elster, Esward, Hessling,
Metrologia 47 (2010) 522).

The filter F(z) = sum_n b_n z^-n (``taps`` coefficients, input the transducer's signal, output the
measurand) minimises sum_k |G(f_k)/G(0)|^2 |F(f_k) - L(f_k) exp(-j 2 pi f_k tau / fs) / G(f_k)|^2, i.e.
the compensated system's error |F G - L e^{-j w tau}|^2 / |G(0)|^2, over a uniform grid f_k of
[0, fs/2] (8 points per tap, at least 512): G the transducer's response, L the regularising
low-pass (Butterworth magnitude 1/sqrt(1 + (f/f_c)^(2 n)), zero phase), tau the delay in samples.
The solution is linear in the target, b = P t(theta) with P the pseudo-inverse of the real-stacked
basis, so the coefficients' covariance is U_b = J Sigma J^T with J = P dt/dtheta and
dt/dtheta = -t (dG/dtheta)/G: exact to first order in the transducer's parameters, and a Monte Carlo
over theta only needs P t(theta_m) (``coefficients_for``).  A FIR filter is stable whatever its
coefficients.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from station.compensate.sensor import Sensor
from station.errors import BadInputError
from station.ident.result import Check
from station.vocabulary import Severity

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]

FILTER_FORMAT = "sinecal-compensation-filter"
FILTER_FORMAT_VERSION = 1
MAX_TAPS = 1024


@dataclass(frozen=True)
class DesignSpec:
    """What the user states: sample rate fs (Hz), band of interest (lo, hi) in Hz, regularising
    low-pass cut-off f_c (Hz, above the band, at most fs/2) and order, taps, delay in samples (None:
    the one of least error over the band), whether a band beyond the calibrated range is accepted
    (with a named finding)."""

    sample_rate_hz: float
    band_hz: tuple[float, float]
    cutoff_hz: float
    taps: int = 64
    lowpass_order: int = 4
    delay_samples: int | None = None
    allow_extrapolation: bool = False

    def check(self) -> None:
        fs, (lo, hi), fc = self.sample_rate_hz, self.band_hz, self.cutoff_hz
        if not (math.isfinite(fs) and fs > 0):
            raise BadInputError(f"sample rate {fs!r} Hz: state a rate > 0 Hz")
        if not (4 <= self.taps <= MAX_TAPS):
            raise BadInputError(f"taps {self.taps}: choose 4 to {MAX_TAPS}")
        if not (1 <= self.lowpass_order <= 16):
            raise BadInputError(f"low-pass order {self.lowpass_order}: choose 1 to 16")
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo < hi < fs / 2):
            raise BadInputError(f"band {lo:g} to {hi:g} Hz: it must lie within 0 Hz and half the sample rate "
                                f"({fs / 2:g} Hz), low edge below the high one")
        if not (math.isfinite(fc) and hi < fc <= fs / 2):
            raise BadInputError(f"cut-off {fc:g} Hz: it must lie above the band ({hi:g} Hz) and at most at half "
                                f"the sample rate ({fs / 2:g} Hz)")
        if self.delay_samples is not None and not (0 <= self.delay_samples < self.taps):
            raise BadInputError(f"delay {self.delay_samples} samples: choose 0 to {self.taps - 1}")


def default_cutoff(band_hi_hz: float, sample_rate_hz: float) -> float:
    """1.5 times the band's upper edge, at most 0.45 fs (Hz)."""
    return min(1.5 * band_hi_hz, 0.45 * sample_rate_hz)


@dataclass(frozen=True)
class Basis:
    """The design grid f (K,) in Hz, the complex basis E (K, taps) = exp(-j 2 pi f n / fs), and
    P (taps, 2K), the pseudo-inverse of [Re E; Im E]."""

    f: FloatArray
    E: ComplexArray
    P: FloatArray

    @classmethod
    def of(cls, taps: int, fs: float, sensor: Sensor | None = None) -> Basis:
        """With a sensor, row k weighs |G(f_k)|/|G(0)|: the fit minimises the compensated system's
        error |F G - L e^{-j w tau}| (relative), not the filter's (absolute, dominated by the high gains
        near the cut-off)."""
        K = max(512, 8 * taps)
        f = np.linspace(0.0, fs / 2, K)
        E = np.exp(-2j * np.pi * np.outer(f, np.arange(taps)) / fs)
        w = np.ones(K) if sensor is None else np.abs(sensor.response(f)) / abs(sensor.response([0.0])[0])
        A = np.vstack([E.real, E.imag])
        W2 = np.concatenate([w, w]) ** 2
        P = np.linalg.solve(A.T @ (W2[:, None] * A), A.T * W2[None, :])  # weighted least squares
        return cls(f, E, P)


def lowpass(f_hz: ArrayLike, cutoff_hz: float, order: int) -> FloatArray:
    """Butterworth magnitude 1/sqrt(1 + (f/f_c)^(2 order)), zero phase (dimensionless)."""
    return 1.0 / np.sqrt(1.0 + (np.asarray(f_hz, dtype=float) / cutoff_hz) ** (2 * order))


def freq_response(b: ArrayLike, f_hz: ArrayLike, fs: float) -> ComplexArray:
    """F(exp(j 2 pi f / fs)) of FIR coefficients b (taps,) or (m, taps) -> (n_f,) or (m, n_f)."""
    bb = np.asarray(b, dtype=float)
    E = np.exp(-2j * np.pi * np.outer(np.asarray(f_hz, dtype=float), np.arange(bb.shape[-1])) / fs)
    return bb @ E.T


def _stack(z: ComplexArray) -> FloatArray:
    return np.concatenate([z.real, z.imag], axis=0)


@dataclass(frozen=True)
class CompensationFilter:
    """A designed filter: coefficients ``b`` (taps,) in unit_out/unit_in, their covariance ``b_cov``
    (taps, taps), the spec it was designed to, the delay it has (samples; fs as in the spec), the
    figures of merit (``fit_rms_band``: RMS over the band of |F G - L e^{-j w tau}|; ``dynamic_error_bound``:
    max over the band of |F G e^{j w tau} - 1|, dimensionless; ``noise_gain``: ||b||_2 in
    unit_out/unit_in), the transducer it inverts and the findings."""

    b: tuple[float, ...]
    b_cov: tuple[tuple[float, ...], ...]
    spec: DesignSpec
    delay_samples: int
    fit_rms_band: float
    dynamic_error_bound: float
    noise_gain: float
    sensor: Sensor
    findings: tuple[Check, ...] = ()
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def b_array(self) -> FloatArray:
        return np.asarray(self.b, dtype=float)

    @property
    def b_cov_array(self) -> FloatArray:
        return np.asarray(self.b_cov, dtype=float).reshape(len(self.b), len(self.b))

    @property
    def sample_rate_hz(self) -> float:
        return self.spec.sample_rate_hz

    @property
    def delay_s(self) -> float:
        return self.delay_samples / self.spec.sample_rate_hz

    @property
    def unit_in(self) -> str:
        return self.sensor.unit_out

    @property
    def unit_out(self) -> str:
        return self.sensor.unit_in

    def to_dict(self) -> dict[str, Any]:
        s = self.spec
        return {"format": FILTER_FORMAT, "format_version": FILTER_FORMAT_VERSION, "kind": "fir",
                "sample_rate_hz": s.sample_rate_hz, "taps": len(self.b), "b": list(self.b),
                "b_cov": [list(r) for r in self.b_cov], "unit_in": self.unit_in, "unit_out": self.unit_out,
                "delay_samples": self.delay_samples, "delay_s": self.delay_s,
                "band_hz": list(s.band_hz), "cutoff_hz": s.cutoff_hz, "lowpass_order": s.lowpass_order,
                "delay_given": s.delay_samples is not None, "allow_extrapolation": s.allow_extrapolation,
                "fit_rms_band": self.fit_rms_band, "dynamic_error_bound": self.dynamic_error_bound,
                "signal_class": "signals whose spectrum lies within the band: |x_hat(t) - x(t)| <= "
                                "dynamic_error_bound * integral of |X(f)| over the band (besides the uncertainty)",
                "noise_gain": self.noise_gain, "stable": True,
                "transducer": self.sensor.to_dict(), "findings": [c.to_dict() for c in self.findings],
                "extra": self.extra}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CompensationFilter:
        if d.get("format") != FILTER_FORMAT or d.get("format_version") != FILTER_FORMAT_VERSION:
            raise BadInputError(f"not a compensation filter of this station (format {d.get('format')!r}, "
                                f"version {d.get('format_version')!r})")
        try:
            b = tuple(float(v) for v in d["b"])
            cov = tuple(tuple(float(v) for v in r) for r in d["b_cov"])
            lo, hi = (float(v) for v in d["band_hz"])
            delay = int(d["delay_samples"])
            spec = DesignSpec(float(d["sample_rate_hz"]), (lo, hi), float(d["cutoff_hz"]), len(b),
                              int(d["lowpass_order"]), delay if d.get("delay_given") else None,
                              bool(d.get("allow_extrapolation")))
            out = cls(b, cov, spec, delay, float(d["fit_rms_band"]), float(d["dynamic_error_bound"]),
                      float(d["noise_gain"]), Sensor.from_dict(d["transducer"]),
                      tuple(Check.from_dict(c) for c in d.get("findings") or ()), dict(d.get("extra") or {}))
        except (KeyError, TypeError, ValueError) as exc:
            raise BadInputError(f"the compensation filter is incomplete or malformed ({exc!r})") from None
        if len(cov) != len(b) or any(len(r) != len(b) for r in cov):
            raise BadInputError("the compensation filter's covariance does not match its coefficients")
        if not (np.all(np.isfinite(out.b_array)) and np.all(np.isfinite(out.b_cov_array))):
            raise BadInputError("the compensation filter has coefficients that are not finite")
        return out


def _target(sensor: Sensor, theta: FloatArray, f: FloatArray, spec: DesignSpec, delays: ArrayLike) -> ComplexArray:
    """L(f) exp(-j 2 pi f tau / fs) / G(f) for each delay: (K, n_delays)."""
    G = sensor.response(f, theta)
    L = lowpass(f, spec.cutoff_hz, spec.lowpass_order)
    ph = np.exp(-2j * np.pi * np.outer(f, np.asarray(delays, dtype=float)) / spec.sample_rate_hz)
    return (L / G)[:, None] * ph


def design_filter(sensor: Sensor, spec: DesignSpec) -> CompensationFilter:
    """The least-squares FIR inverse of ``sensor`` to ``spec``, with its coefficients' covariance.

    Refused: a spec out of range; a band above the calibrated range unless ``allow_extrapolation``
    (then the finding ``extrapolation`` names it); a transducer whose response vanishes on the grid;
    coefficients that are not finite."""
    spec.check()
    findings = list(sensor.findings)
    lo_cal, hi_cal = sensor.calibrated_range_hz
    if math.isfinite(hi_cal) and spec.band_hz[1] > hi_cal * (1 + 1e-9):
        msg = (f"the band reaches {spec.band_hz[1]:g} Hz, beyond the calibrated range {lo_cal:g} to {hi_cal:g} Hz: "
               f"there the filter rests on the model ({sensor.assumptions.get('model', sensor.kind)}), "
               "not on measured values")
        if not spec.allow_extrapolation:
            raise BadInputError(msg + "; refused (accept it with --allow-extrapolation)")
        findings.append(Check("extrapolation", Severity.WARNING, None, msg,
                              {"band_hz": list(spec.band_hz), "calibrated_range_hz": [lo_cal, hi_cal]}))
    fs, N = spec.sample_rate_hz, spec.taps
    basis = Basis.of(N, fs, sensor)
    theta = sensor.theta_array
    G = sensor.response(basis.f, theta)
    if not np.all(np.isfinite(G)) or np.any(np.abs(G) == 0):
        raise BadInputError("the transducer's response vanishes or is not finite on the design grid")
    fb = np.linspace(spec.band_hz[0], spec.band_hz[1], 256)
    Gb = sensor.response(fb, theta)
    Lb = lowpass(fb, spec.cutoff_hz, spec.lowpass_order)
    delays = np.arange(N) if spec.delay_samples is None else np.array([spec.delay_samples])
    B = (basis.P @ _stack(_target(sensor, theta, basis.f, spec, delays))).T  # (n_delays, N)
    Fb = freq_response(B, fb, fs)  # (n_delays, n_band)
    ideal = Lb[None, :] * np.exp(-2j * np.pi * np.outer(delays, fb) / fs)
    rms = np.sqrt(np.mean(np.abs(Fb * Gb[None, :] - ideal) ** 2, axis=1))
    i = int(np.argmin(rms))
    tau = int(delays[i])
    b = B[i]
    if not np.all(np.isfinite(b)):
        raise BadInputError("the design gave coefficients that are not finite: choose a lower cut-off or more taps")
    t = _target(sensor, theta, basis.f, spec, [tau])[:, 0]
    dt = -t[:, None] * sensor.jacobian(basis.f) / G[:, None]  # (K, p)
    Jb = basis.P @ _stack(dt)  # (N, p)
    Ub = Jb @ sensor.cov_array @ Jb.T
    Ub = 0.5 * (Ub + Ub.T)
    Hc = Fb[i] * Gb * np.exp(2j * np.pi * fb * tau / fs)
    bound = float(np.max(np.abs(Hc - 1.0)))
    if bound > 0.1:
        findings.append(Check("dynamic_error", Severity.WARNING, None,
                              f"within the band the compensated system departs from 1 by up to {bound:.3g} "
                              "(relative): widen the cut-off, add taps or narrow the band", {"bound": bound}))
    return CompensationFilter(tuple(float(v) for v in b), tuple(tuple(float(v) for v in r) for r in Ub), spec, tau,
                              float(rms[i]), bound, float(np.linalg.norm(b)), sensor, tuple(findings),
                              {"sensitivity_matrix": Jb.tolist()})


def coefficients_for(filt: CompensationFilter, thetas: ArrayLike) -> FloatArray:
    """The filter's coefficients redesigned (same spec, same delay) for transducer parameters
    ``thetas`` (m, p): (m, taps).  The Monte Carlo's draws (GUM-S1) go through this, not through the
    linearisation."""
    spec = filt.spec
    basis = Basis.of(len(filt.b), spec.sample_rate_hz, filt.sensor)
    th = np.atleast_2d(np.asarray(thetas, dtype=float))
    L = lowpass(basis.f, spec.cutoff_hz, spec.lowpass_order) * np.exp(
        -2j * np.pi * basis.f * filt.delay_samples / spec.sample_rate_hz)
    T = np.empty((2 * basis.f.size, th.shape[0]))
    for m, theta in enumerate(th):
        T[:, m] = _stack(L / filt.sensor.response(basis.f, theta))
    return (basis.P @ T).T


@dataclass(frozen=True)
class Bode:
    """Frequency responses on ``f`` (Hz): transducer G, filter F, compensated system Hc = F G
    exp(j 2 pi f tau/fs) (delay removed), each with the standard uncertainty of its magnitude
    (relative) and phase (rad)."""

    f: FloatArray
    G: ComplexArray
    u_G_rel: FloatArray
    u_G_phase: FloatArray
    F: ComplexArray
    u_F_rel: FloatArray
    Hc: ComplexArray
    u_Hc_rel: FloatArray
    u_Hc_phase: FloatArray


def bode(filt: CompensationFilter, n: int = 400) -> Bode:
    """The Bode data of a designed filter from 0 to fs/2 (first point at fs/(4 n))."""
    fs = filt.sample_rate_hz
    f = np.linspace(fs / (4 * n), fs / 2, n)
    s = filt.sensor
    G = s.response(f)
    uG, uGp = s.response_std(f)
    E = np.exp(-2j * np.pi * np.outer(f, np.arange(len(filt.b))) / fs)
    F = E @ filt.b_array
    dF = E @ np.asarray(filt.extra["sensitivity_matrix"], dtype=float) if "sensitivity_matrix" in filt.extra \
        else np.zeros((f.size, len(s.theta)), complex)
    ph = np.exp(2j * np.pi * f * filt.delay_samples / fs)
    Hc = F * G * ph
    dHc = (dF * G[:, None] + F[:, None] * s.jacobian(f)) * ph[:, None]
    C = s.cov_array
    dlog = dHc / np.where(Hc == 0, 1, Hc)[:, None]
    uH = np.sqrt(np.clip(np.einsum("ij,jk,ik->i", dlog.real, C, dlog.real), 0, None))
    uHp = np.sqrt(np.clip(np.einsum("ij,jk,ik->i", dlog.imag, C, dlog.imag), 0, None))
    dlogF = dF / np.where(F == 0, 1, F)[:, None]
    uF = np.sqrt(np.clip(np.einsum("ij,jk,ik->i", dlogF.real, C, dlogF.real), 0, None))
    return Bode(f, G, uG, uGp, F, uF, Hc, uH, uHp)
