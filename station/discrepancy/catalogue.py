"""The effect catalogue as the fits see it: parameters, units, scales, bounds and start values.

Internal fit variables u are O(1): a linear parameter is value = centre + scale * u, a positive one
fitted in logarithm is value = centre * exp(u * scale).  A stiffness or frequency whose effect vanishes
as it grows (the coupling's k_c, the low-pass cut-off, the displacement sensor's resonance) is fitted as
its reciprocal, 1 / value = 1 / centre + scale * u: the effect's absence (a rigid coupling, no low-pass)
is then a bound at a finite distance, which the fit reaches in a few steps, where in logarithm the model
flattens towards it and the fit would crawl there for its whole budget of evaluations.  Effects are
named as in ``drivers.rig.params.Effects``; the low-pass order is a discrete parameter fitted by
enumeration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.rig.params import EFFECT_NAMES
from station.discrepancy.data import RigData, per_data_set

# the effects the force model can name; the crank harmonics are not among them: the model takes the
# frame motion as recorded, and ``drive`` checks it against the slider crank; nor is the transducer's
# ageing, a change between runs that one run's data cannot show (the control charts do)
CATALOGUE: tuple[str, ...] = tuple(e for e in EFFECT_NAMES if e not in ("crank_harmonics", "ageing"))
LOWPASS_ORDERS: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 7, 8)


@dataclass(frozen=True)
class Param:
    """One fit parameter: name, SI unit, log (fitted as log of a positive value), reciprocal (fitted as
    1 / value, module docstring), lower/upper bound, additive (the model is affine in it with a
    coefficient no other parameter changes: its Jacobian column is constant, ``fit.Problem.jacobian``)."""

    name: str
    unit: str
    log: bool = False
    reciprocal: bool = False
    lower: float = -np.inf
    upper: float = np.inf
    additive: bool = False


BASE_PARAMS: tuple[Param, ...] = (
    Param("S", "V/N"), Param("k_f", "N/m", log=True, lower=1.0, upper=1e13),
    Param("b_f", "N*s/m", log=True, lower=1e-6, upper=1e9),
    Param("offset_V", "V", additive=True),
)


def effect_params(name: str, data: RigData) -> tuple[Param, ...]:
    """Parameters an effect adds to the model."""
    if name == "coupling_compliance":
        return (Param("k_c", "N/m", reciprocal=True, lower=1e2, upper=1e14), Param("b_c", "N*s/m", lower=0.0))
    if name == "conditioner_lowpass":
        return (Param("cutoff_hz", "Hz", reciprocal=True, lower=0.1, upper=1e7),)
    if name == "channel_delay":
        return (Param("delay_s", "s", lower=-5e-3, upper=5e-3),)
    if name == "crank_harmonics":
        return (Param("inverse_rod_length_per_m", "1/m"),)
    if name == "transducer_nonlinearity":
        return (Param("quadratic", "1", lower=-1.0, upper=1.0), Param("cubic", "1", lower=-1.0, upper=1.0))
    if name == "mains_interference":
        if not data.common_clock:  # phases not comparable between steps: a phasor per step and line
            return tuple(Param(f"{c}_{h}_s{i}", "V", additive=True) for i in range(data.n_steps)
                         for h in range(1, data.n_mains + 1) for c in ("re", "im"))
        out = [Param("frequency_hz", "Hz", lower=40.0, upper=70.0)]
        for h in range(1, data.n_mains + 1):
            out += [Param(f"re_{h}", "V"), Param(f"im_{h}", "V")]
        return tuple(out)
    if name == "displacement_resonance":  # the sensor's own resonance (drivers.rig.params.DisplacementResonance)
        return (Param("sensor_resonance_hz", "Hz", reciprocal=True, lower=float(data.f_hz.max()),
                      upper=1e6),
                Param("sensor_damping", "1", lower=0.0, upper=10.0))
    if name == "clock_skew":  # the force converter's clock against the displacement converter's
        return (Param("clock_skew", "1", lower=-1e-3, upper=1e-3),)
    if name == "zero_drift":
        if not data.common_clock:  # no common time axis: each step's own offset, slope and curvature
            return tuple([Param(f"dc_s{i}", "V", additive=True) for i in range(1, data.n_steps)]
                         + [Param(f"{c}_s{i}", "V", additive=True) for i in range(data.n_steps)
                            for c in ("slope", "curv")])
        return (Param("rate_V_per_s", "V/s", additive=True), Param("quadratic_V_per_s2", "V/s^2", additive=True))
    raise KeyError(f"unknown effect {name!r}; the catalogue is {', '.join(CATALOGUE)}")


NEUTRAL: dict[str, float] = {
    "k_c": np.inf, "b_c": 0.0, "cutoff_hz": np.inf, "delay_s": 0.0, "inverse_rod_length_per_m": 0.0,
    "quadratic": 0.0, "cubic": 0.0, "rate_V_per_s": 0.0, "quadratic_V_per_s2": 0.0,
    "sensor_resonance_hz": np.inf, "sensor_damping": 0.0, "clock_skew": 0.0,
}


# the top of the start grids of the reciprocal parameters: k_c / k_f, cut-off and sensor resonance over the
# highest crank frequency (``start_grid``; ``scales`` takes a reciprocal's step from them)
KC_TOP, CUTOFF_TOP, RESONANCE_TOP = 3000.0, 300.0, 300.0


@per_data_set(4)
def _data_scales(data: RigData) -> tuple[float, float, float, dict[str, float]]:
    """What ``scales`` takes of a data set alone, once per data set: the median noise sigma (V), the
    record's duration (s), the highest crank frequency (Hz) and the per-step parameters' scales
    (10 sigma, in ``scales``' order)."""
    sig = float(np.median(data.sigma_f))
    per_step: dict[str, float] = {}
    for i in range(data.n_steps):
        per_step[f"dc_s{i}"] = per_step[f"slope_s{i}"] = per_step[f"curv_s{i}"] = 10 * sig
    for h in range(1, data.n_mains + 1):
        per_step[f"re_{h}"] = per_step[f"im_{h}"] = 10 * sig
        for i in range(data.n_steps):
            per_step[f"re_{h}_s{i}"] = per_step[f"im_{h}_s{i}"] = 10 * sig
    return sig, float(data.t_mid_s.max() + data.half_s.max()), float(data.f_hz.max()), per_step


def scales(p: dict[str, float], data: RigData) -> dict[str, float]:
    """Typical size of one fit step per parameter (linear: absolute, log: relative, reciprocal: of
    1 / value, a tenth of 1 / value at the start, or of the top of its start grid where the start is
    beyond that top (a start in the rigid limit still moves in a few steps))."""
    sig, T, fmax, per_step = _data_scales(data)

    def recip(name: str, top: float) -> float:
        return 0.1 / min(abs(p.get(name, np.inf)), top)

    out = {"S": 1e-3 * abs(p["S"]), "k_f": 1e-3, "b_f": 1e-2, "offset_V": 1e2 * sig,
           "k_c": recip("k_c", KC_TOP * p["k_f"]), "b_c": 0.1 * p["b_f"],
           "cutoff_hz": recip("cutoff_hz", CUTOFF_TOP * fmax), "delay_s": 1e-6, "inverse_rod_length_per_m": 0.1,
           "quadratic": 1e-3, "cubic": 1e-3, "frequency_hz": 1e-3,
           "sensor_resonance_hz": recip("sensor_resonance_hz", RESONANCE_TOP * fmax), "sensor_damping": 0.05,
           "rate_V_per_s": 10 * sig / T,
           "quadratic_V_per_s2": 10 * sig / T**2, "clock_skew": 1e-6}
    out.update(per_step)
    return out


def absent(name: str, data: RigData) -> dict[str, float] | None:
    """The effect's parameters where it (all but) vanishes from the model, for an effect whose absence
    is a bound (a reciprocal parameter at its upper bound: a rigid coupling, no low-pass; the others at
    their neutral value); None for the others (their neutral values are in their start grids)."""
    params = effect_params(name, data)
    if not any(q.reciprocal for q in params):
        return None
    return {q.name: q.upper if q.reciprocal else NEUTRAL[q.name] for q in params}


def start_grid(name: str, data: RigData, p: dict[str, float]) -> list[dict[str, float]]:
    """Start values of an effect's parameters (several for the nonlinear ones); ``search`` picks the
    best of them (or the effect's absence, ``absent``) before the Levenberg-Marquardt fit."""
    fmax = float(data.f_hz.max())
    if name == "coupling_compliance":
        return [{"k_c": p["k_f"] * r, "b_c": b} for r in np.geomspace(0.3, KC_TOP, 9)
                for b in (0.0, p["b_f"])]
    if name == "conditioner_lowpass":
        return [{"cutoff_hz": fc} for fc in np.geomspace(0.5 * fmax, CUTOFF_TOP * fmax, 13)]
    if name == "channel_delay":
        return [{"delay_s": d} for d in (0.0, -1e-4, 1e-4, -5e-4, 5e-4)]
    if name == "clock_skew":
        return [{"clock_skew": e} for e in (0.0, -1e-4, 1e-4)]
    if name == "displacement_resonance":
        return [{"sensor_resonance_hz": fr, "sensor_damping": z}
                for fr in np.geomspace(3 * fmax, RESONANCE_TOP * fmax, 5)
                for z in (0.1, 0.7)]
    if name == "crank_harmonics":
        r = np.abs(data.x1)
        d2 = np.abs(data.cd[:, 0] - 1j * data.cd[:, 1])
        ok = data.kmask[:, 1] & (r > 0)
        kap = float(np.median(4 * d2[ok] / r[ok] ** 2)) if np.any(ok) else 1.0
        return [{"inverse_rod_length_per_m": s * kap} for s in (1.0, -1.0)]
    if name == "transducer_nonlinearity":
        return [{"quadratic": 0.0, "cubic": 0.0}]
    if name == "mains_interference":
        return [mains_start(data)]
    if name == "zero_drift":
        if not data.common_clock:
            return [{q.name: 0.0 for q in effect_params(name, data)}]
        return [{"rate_V_per_s": 0.0, "quadratic_V_per_s2": 0.0}]
    raise KeyError(name)


def mains_start(data: RigData) -> dict[str, float]:
    """Coherent start for the mains lines: the measured line phasors W_ih (own slots only) against
    Q_h exp(j h 2 pi f_m t_i); f_m maximises sum_h |sum_i W_ih exp(-j h 2 pi f_m t_i)|^2 within
    +-0.15 Hz of the detected frequency, Q_h is then the mean demodulated phasor (V)."""
    f0 = data.mains.frequency_hz or 50.0
    K = (data.cf.shape[1] - 3 - 2 * data.n_mains) // 2
    a = data.cf[:, 2 * K + 3 :: 2]
    b = data.cf[:, 2 * K + 4 :: 2]
    W = (a - 1j * b) * (data.merge == 0)
    if not data.common_clock:  # each step's own phasors (lines merged with a crank harmonic: 0)
        return {f"{c}_{h}_s{i}": float(getattr(W[i, h - 1], "real" if c == "re" else "imag"))
                for i in range(data.n_steps) for h in range(1, data.n_mains + 1) for c in ("re", "im")}
    hh = np.arange(1, data.n_mains + 1)[None, None, :]
    grid = f0 + np.linspace(-0.15, 0.15, 1201)
    ph = np.exp(-1j * hh * 2 * np.pi * grid[:, None, None] * data.t_mid_s[None, :, None])
    power = np.sum(np.abs(np.sum(W[None] * ph, axis=1)) ** 2, axis=1)
    j = int(np.argmax(power))
    cnt = np.maximum(np.sum(data.merge == 0, axis=0), 1)
    Q = np.sum(W * ph[j], axis=0) / cnt
    out = {"frequency_hz": float(grid[j])}
    for h in range(1, data.n_mains + 1):
        out[f"re_{h}"], out[f"im_{h}"] = float(Q[h - 1].real), float(Q[h - 1].imag)
    return out
