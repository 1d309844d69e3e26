"""Plausibility gate: every step and the run are checked before (and after) any model fit.

Each finding is a named ``Check`` (severity info, warning or refused).  A step with a dead,
constant, clipped, non-finite or signal-free channel, a frequency fit that runs away, or a
displacement amplitude unlike its crank radius is left out with its reason (never a crash, never
the run's end).  A run is refused when what is left cannot give a right answer: displacement in
other units (amplitude / radius ~ 1000 for mm), swapped channels, a low-frequency gain that is not
S_nominal (m_l + m_e) within a factor 2 (a mass or sensitivity typed wrong), no usable step.
The frequency of each step is measured (FFT peak, then the four-parameter fit from there), never
taken from the label: a slipping crank or a mislabelled step is fitted at its real frequency and
named.  Polarity is detected; either sign of S is legal.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from station.errors import BadInputError
from station.ident.response import frf as frfmod
from station.ident.result import Check, json_float
from station.jsonvalue import JsonValue
from station.vocabulary import Severity

FloatArray = NDArray[np.float64]
MIN_SNR = 10.0  # fundamental amplitude over its standard deviation
FREQ_TOL = 0.005  # relative deviation of the measured from the labelled frequency that is named
AMP_TOL = 0.05  # relative deviation of the displacement amplitude from the crank radius that is named
GAIN_WARN, GAIN_REFUSE = 0.10, 2.0  # low-frequency gain vs S_nominal M: warn beyond 10 %, refuse beyond 2x
MAX_QUASI_STATIC_LAG_DEG = 20.0  # ... refuse only where the phase lag shows the step is quasi-static


class IdentificationRefused(BadInputError):
    """The inputs cannot give a right answer; ``checks`` holds every finding, the refusing ones
    with severity 'refused'."""

    def __init__(self, message: str, checks: list[Check]) -> None:
        super().__init__(message)
        self.checks = checks


def coarse_frequency(x: FloatArray, fs_hz: float) -> float:
    """Frequency of the strongest spectral line (mean removed, Hann window, parabolic interpolation
    of the log magnitude: a small fraction of a bin), Hz.  Lines below one cycle per record are not
    a crank frequency (the mean's leftover); a line of two cycles per record is (its Hann main lobe
    reaches down to DC, so only the bins below one cycle are left out)."""
    n = x.size
    nfft = 1 << int(np.ceil(np.log2(n)))
    spec = np.abs(np.fft.rfft((x - np.mean(x)) * np.hanning(n), nfft))
    cut = int(np.ceil(nfft / n))  # fft bins below one cycle per record
    spec[:cut] = 0.0
    k = int(np.argmax(spec))
    kf = float(k)
    if cut < k < spec.size - 1:
        a, b, c = np.log(spec[k - 1:k + 2] + 1e-300)
        den = a - 2 * b + c
        kf += 0.5 * (a - c) / den if den != 0 else 0.0
    return kf * fs_hz / nfft


def _clipped(y: FloatArray) -> float | None:
    """Fraction of samples sitting on the extreme value when more than an unclipped (quantised)
    sine would put there (within one quantisation step q of its peak: sqrt(2 q / A) / pi); None when
    not clipped.  q: the smallest nonzero step between consecutive samples."""
    hi, lo = float(np.max(y)), float(np.min(y))
    frac = max(np.count_nonzero(y == hi), np.count_nonzero(y == lo)) / y.size
    if frac <= 0.005 or hi == lo:
        return None
    d = np.abs(np.diff(y))
    q = float(np.min(d[d > 0])) if np.any(d > 0) else 0.0
    expected = np.sqrt(2 * q / ((hi - lo) / 2)) / np.pi
    return float(frac) if frac > 3 * expected + 0.005 else None


def _channel_checks(idx: int, name: str, y: FloatArray) -> Check | None:
    if not np.all(np.isfinite(y)):
        return Check("non_finite_channel", Severity.WARNING, idx, f"step {idx} left out: the {name} channel "
                     f"holds {int(np.count_nonzero(~np.isfinite(y)))} non-finite samples", {"channel": name})
    if np.all(y == 0):
        return Check("dead_channel", Severity.WARNING, idx, f"step {idx} left out: the {name} channel is all "
                     "zeros (not connected, or a dead channel)", {"channel": name})
    if np.ptp(y) == 0:
        return Check("constant_channel", Severity.WARNING, idx, f"step {idx} left out: the {name} channel is "
                     f"constant ({float(y[0]):.6g}) over the step", {"channel": name, "value": float(y[0])})
    frac = _clipped(y)
    if frac is not None:
        return Check("clipped_channel", Severity.WARNING, idx, f"step {idx} left out: the {name} channel sits "
                     f"on its extreme value in {100 * frac:.2g} % of the samples (clipped)",
                     {"channel": name, "fraction": frac})
    return None


def screen_step(idx: int, t: FloatArray, x: FloatArray, u: FloatArray, f_label_hz: float, radius_m: float,
                fs_hz: float, n_harmonics: int = 3) -> tuple[frfmod.StepItem | None, list[Check]]:
    """Checks one step and measures its H.  Returns (step_response item or None if left out, checks)."""
    for name, y in (("displacement", x), ("force", u)):
        c = _channel_checks(idx, name, y)
        if c is not None:
            return None, [c]
    checks: list[Check] = []
    f0 = coarse_frequency(x, fs_hz)
    try:
        item = frfmod.step_response(t, x, u, f0, n_harmonics=n_harmonics)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:
        return None, [Check("step_failed", Severity.WARNING, idx, f"step {idx} left out: its sine fit failed "
                            f"({exc})", {})]
    fx, fu = item[2], item[3]
    f = fx.frequency_hz
    bin_hz = fs_hz / x.size
    if (not np.isfinite(f) or abs(f - f0) > bin_hz) and abs(f0 / f_label_hz - 1) > FREQ_TOL:
        # a window of a few cycles: the sine's spectral line merges with the leakage of the mean, and
        # the peak can be off by more than the fit's reach; the labelled frequency is the other start
        try:
            again = frfmod.step_response(t, x, u, f_label_hz, n_harmonics=n_harmonics)
        except (np.linalg.LinAlgError, ValueError, FloatingPointError):
            again = None
        if again is not None and np.isfinite(again[2].frequency_hz) \
                and abs(again[2].frequency_hz - f_label_hz) <= bin_hz:
            item, f0 = again, f_label_hz
            fx, fu = item[2], item[3]
            f = fx.frequency_hz
    if not np.isfinite(f) or abs(f - f0) > bin_hz:
        return None, [Check("frequency_fit_diverged", Severity.WARNING, idx, f"step {idx} left out: the frequency "
                            f"fit went from {f0:.6g} Hz to {f:.6g} Hz", {"spectral_peak_hz": f0,
                                                                         "fitted_hz": float(f)})]
    for name, fit in (("displacement", fx), ("force", fu)):
        snr = abs(fit.phasor) / max(np.sqrt(np.trace(fit.phasor_cov) / 2), 1e-300)
        if snr < MIN_SNR:
            return None, [Check("no_signal", Severity.WARNING, idx, f"step {idx} left out: the {name} channel "
                                f"shows no sine at {f:.6g} Hz (amplitude {snr:.2g} standard deviations, "
                                f"{MIN_SNR:g} needed): noise only", {"channel": name, "snr": float(snr)})]
    rel = f / f_label_hz - 1
    if abs(rel) > FREQ_TOL and abs(f - f_label_hz) > 5 * fx.frequency_std_hz:
        checks.append(Check("frequency_mismatch", Severity.WARNING, idx, f"step {idx} ran at {f:.6g} Hz, labelled "
                            f"{f_label_hz:g} Hz ({100 * rel:+.3g} %): crank slip or a mislabelled step; "
                            "fitted at the measured frequency", {"measured_hz": float(f),
                                                                  "labelled_hz": f_label_hz, "relative": rel}))
    ratio = abs(fx.phasor) / radius_m
    if abs(ratio - 1) > AMP_TOL:
        checks.append(Check("displacement_amplitude", Severity.WARNING, idx, f"step {idx}: displacement amplitude "
                            f"{abs(fx.phasor):.4g} m against a crank radius of {radius_m:.4g} m "
                            f"(ratio {ratio:.4g})", {"amplitude_m": abs(fx.phasor), "radius_m": radius_m,
                                                     "ratio": ratio, "force_amplitude_V": abs(fu.phasor)}))
    return item, checks


def _units_hint(ratio: float) -> str:
    for factor, unit in ((1e3, "mm"), (1e6, "µm"), (1e2, "cm"), (1e-3, "km")):
        if abs(np.log10(ratio / factor)) < 0.15:
            return f" (about {factor:g}: the displacement column is likely in {unit}, not m)"
    return ""


def run_checks(items: dict[int, frfmod.StepItem], step_checks: list[Check], radii: dict[int, float],
               sensitivity_nominal: float, mass_kg: float) -> tuple[list[Check], list[int], float]:
    """Run-level checks on the screened steps.  Returns (new checks, steps still used, polarity sign
    +1/-1 of S).  Raises IdentificationRefused with every check when the run cannot be identified."""
    out: list[Check] = []
    used = sorted(items)
    amp = {c.step: c.values for c in step_checks if c.name == "displacement_amplitude"}
    bad = [i for i in used if i in amp and not 1 / 3 < json_float(amp[i], "ratio") < 3]
    if used and len(bad) == len(used):
        r = float(np.median([json_float(amp[i], "ratio") for i in bad]))
        swapped = [i for i in bad if abs(json_float(amp[i], "force_amplitude_V") / radii[i] - 1) < 0.25]
        if len(swapped) == len(bad):
            out.append(Check("channels_swapped", Severity.REFUSED, None, "the displacement and force columns look "
                             f"swapped: the force channel's amplitude matches the crank radius, the "
                             f"displacement's is {r:.4g} times it", {"ratio": r}))
        else:
            out.append(Check("displacement_units", Severity.REFUSED, None, f"the displacement amplitude is {r:.4g} "
                             f"times the crank radius in every step{_units_hint(r)}; displacement in m "
                             "expected", {"ratio": r}))
    else:
        for i in bad:
            used.remove(i)
            out.append(Check("displacement_amplitude", Severity.WARNING, i, f"step {i} left out: its displacement "
                             f"amplitude is {amp[i]['ratio']:.4g} times its crank radius", amp[i]))
    if not used or any(c.severity == "refused" for c in out):
        if not any(c.severity == "refused" for c in out):
            out.append(Check("no_usable_step", Severity.REFUSED, None, "no usable step is left", {}))
        raise IdentificationRefused("; ".join(c.message for c in out if c.severity == "refused"),
                                    step_checks + out)
    low = min(used, key=lambda i: items[i][2].frequency_hz)
    H = items[low][0]
    sign = -1.0 if H.real > 0 else 1.0
    nominal_sign = 1.0 if sensitivity_nominal > 0 else -1.0
    if sign < 0 or nominal_sign < 0:
        agree = sign == nominal_sign
        out.append(Check("polarity", Severity.INFO if agree else Severity.WARNING, None, "inverted polarity: the force "
                         "signal rises with the inertia force, S is negative" if sign < 0 else
                         "normal polarity: S is positive", {"sign": sign, "nominal_sign": nominal_sign}))
        if not agree:
            out[-1] = Check("polarity", Severity.WARNING, None, f"the data give S the sign {sign:+.0f}, the nominal "
                            f"sensitivity has {nominal_sign:+.0f}; S is reported with the data's sign",
                            {"sign": sign, "nominal_sign": nominal_sign})
    f_low = items[low][2].frequency_hz
    g = abs(H) / (abs(sensitivity_nominal) * mass_kg)
    vals: dict[str, JsonValue] = {"frequency_hz": f_low, "gain_ratio": g, "H_abs": abs(H), "mass_kg": mass_kg,
            "sensitivity_nominal_V_per_N": sensitivity_nominal}
    text = (f"|H| at {f_low:.4g} Hz is {g:.4g} times |S_nominal| (m_l + m_e) = "
            f"{abs(sensitivity_nominal):.4g} V/N x {mass_kg:.5g} kg")
    lag = float(np.degrees(abs(np.angle(-H * sign))))  # ~0 far below the resonance, whatever the masses
    vals["phase_lag_deg"] = lag
    if not 1 / GAIN_REFUSE < g < GAIN_REFUSE and lag < MAX_QUASI_STATIC_LAG_DEG:
        out.append(Check("low_frequency_gain", Severity.REFUSED, None, text + ": a top mass or the sensitivity "
                         "typed wrong (e.g. by a factor 10), or the force signal in other units", vals))
        raise IdentificationRefused(out[-1].message, step_checks + out)
    if not 1 / GAIN_REFUSE < g < GAIN_REFUSE:
        out.append(Check("low_frequency_gain", Severity.WARNING, None, text + f" with a phase lag of {lag:.3g} deg: "
                         "the lowest step is near the resonance, so the gain cannot tell a mass or "
                         "sensitivity typed wrong", vals))
        return out, used, sign
    if abs(g - 1) > GAIN_WARN:
        out.append(Check("low_frequency_gain", Severity.WARNING, None, text + " (resonance amplification, or a "
                         "mass or the nominal sensitivity off)", vals))
    return out, used, sign


def sensitivity_check(S: float | None, nominal: float, conditional: bool) -> Check | None:
    """Identified S against the nominal sensitivity (warning beyond 10 %)."""
    if S is None or not np.isfinite(S):
        return None
    r = S / nominal
    if abs(abs(r) - 1) <= GAIN_WARN:
        return None
    return Check("sensitivity_vs_nominal", Severity.WARNING, None, f"identified S = {S:.6g} V/N is {abs(r):.4g} times "
                 f"the nominal {nominal:.6g} V/N" + (" (conditional on the assumed end mass)" if conditional
                                                    else ""), {"ratio": float(abs(r))})
