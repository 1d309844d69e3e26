"""The parameters of a model-gap fit as estimates: the transducer's (S, k_f, b_f, and k_c, b_c with
the coupling) and each catalogue effect's, in the units of ``drivers.rig.params``."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from station.discrepancy.fit import ModelFit
from station.ident.result import Estimate

ORDER_AMBIGUITY = 10.0  # chi^2 units (times the Birge ratio): low-pass orders closer than this tie
EstimateJson = Mapping[str, object]  # ``Estimate.to_dict``: value, std, unit (SI, as the quantity's name says)
TRANSDUCER = (("S", "V/N"), ("k_f", "N/m"), ("b_f", "N*s/m"))


def transducer_parameters(fit: ModelFit) -> dict[str, Estimate]:
    """S, k_f, b_f (and k_c, b_c when the coupling is in the model) as in ``station identify``."""
    out = {n: Estimate(fit.values[n], fit.std[n], u) for n, u in TRANSDUCER}
    if "coupling_compliance" in fit.effects:
        out.update(effect_estimates(fit, "coupling_compliance"))
    return out


def _idx(fit: ModelFit, name: str) -> int:
    return [q.name for q in fit.params].index(name)


def effect_estimates(fit: ModelFit, name: str) -> dict[str, Estimate]:
    """The effect's parameters in the units of ``drivers.rig.params`` (derived ones by the delta
    method: rod length L = 1/kappa, mains amplitude |Q_h| and phase angle(Q_h) + pi/2 of
    a sin(h w t + phase))."""
    v, s = fit.values, fit.std
    if name == "coupling_compliance":
        return {"k_c": Estimate(v["k_c"], s["k_c"], "N/m"), "b_c": Estimate(v["b_c"], s["b_c"], "N*s/m")}
    if name == "conditioner_lowpass":
        order = fit.effects[name]
        close = [a for a in fit.alternatives if a[0] != order and a[1] - fit.chi2 < ORDER_AMBIGUITY * fit.birge]
        est = {"order": Estimate(float(order), 0.0, "1"), "cutoff_hz": Estimate(v["cutoff_hz"], s["cutoff_hz"], "Hz")}
        if close:
            why = (f"orders {', '.join(str(a[0]) for a in close)} fit as well (Delta chi2 < {ORDER_AMBIGUITY:g}); "
                   f"k_f would be {', '.join(f'{a[2]:.6g}' for a in close)} N/m")
            est["order"] = Estimate(float(order), math.nan, "1", False, why)
        return est
    if name == "channel_delay":
        return {"delay_s": Estimate(v["delay_s"], s["delay_s"], "s")}
    if name == "clock_skew":
        return {"clock_skew": Estimate(v["clock_skew"], s["clock_skew"], "1")}
    if name == "displacement_resonance":
        return {"resonance_hz": Estimate(v["sensor_resonance_hz"], s["sensor_resonance_hz"], "Hz"),
                "damping": Estimate(v["sensor_damping"], s["sensor_damping"], "1")}
    if name == "crank_harmonics":
        kap, sk = v["inverse_rod_length_per_m"], s["inverse_rod_length_per_m"]
        if abs(kap) <= 2 * sk:
            return {"rod_length_m": Estimate(math.nan, math.nan, "m", False,
                                             f"1/L = {kap:.3g} +- {sk:.3g} 1/m is not distinct from 0")}
        return {"rod_length_m": Estimate(1 / kap, sk / kap**2, "m")}
    if name == "transducer_nonlinearity":
        return {"quadratic": Estimate(v["quadratic"], s["quadratic"], "1"),
                "cubic": Estimate(v["cubic"], s["cubic"], "1")}
    if name == "zero_drift" and "slope_s0" in v:
        why = ("the steps have their own time origins: the drift is fitted as each step's own offset, slope and "
               "curvature, and a rate over the run is not determined")
        return {"rate_V_per_s": Estimate(math.nan, math.nan, "V/s", False, why),
                "quadratic_V_per_s2": Estimate(math.nan, math.nan, "V/s^2", False, why)}
    if name == "zero_drift":
        return {"rate_V_per_s": Estimate(v["rate_V_per_s"], s["rate_V_per_s"], "V/s"),
                "quadratic_V_per_s2": Estimate(v["quadratic_V_per_s2"], s["quadratic_V_per_s2"], "V/s^2")}
    if name == "mains_interference" and "frequency_hz" not in v:
        return _mains_per_step(fit)
    if name == "mains_interference":
        out = {"frequency_hz": Estimate(v["frequency_hz"], s["frequency_hz"], "Hz")}
        h = 1
        while f"re_{h}" in v:
            i, j = _idx(fit, f"re_{h}"), _idx(fit, f"im_{h}")
            C = fit.cov[np.ix_([i, j], [i, j])]
            re, im = v[f"re_{h}"], v[f"im_{h}"]
            a = math.hypot(re, im)
            ga = np.array([re, im]) / max(a, 1e-300)
            gp = np.array([-im, re]) / max(a, 1e-300) ** 2
            out[f"amplitude_V_{h}"] = Estimate(a, math.sqrt(float(ga @ C @ ga)), "V")
            phase = (math.atan2(im, re) + 1.5 * math.pi) % (2 * math.pi) - math.pi
            out[f"phase_rad_{h}"] = Estimate(phase, math.sqrt(float(gp @ C @ gp)),
                                             "rad")
            h += 1
        return out
    raise KeyError(name)


NO_CLOCK = ("the steps have their own time origins (their windows overlap on the recorded time axis): the "
            "phase of a line between steps is unknown, so its frequency (and phase) is not determined")


def _mains_per_step(fit: ModelFit) -> dict[str, Estimate]:
    """Mains lines fitted with a phasor per step (no common clock): frequency and phases not
    identifiable; the amplitude of line h as the mean of its per-step amplitudes (V), standard
    uncertainty from their scatter (or the fit's, if larger) over sqrt(n)."""
    v = fit.values
    out = {"frequency_hz": Estimate(math.nan, math.nan, "Hz", False, NO_CLOCK)}
    h = 1
    while f"re_{h}_s0" in v:
        amps, i = [], 0
        while f"re_{h}_s{i}" in v:
            amps.append(math.hypot(v[f"re_{h}_s{i}"], v[f"im_{h}_s{i}"]))
            i += 1
        a = np.array(amps)
        fit_sd = max(fit.std[f"re_{h}_s0"], fit.std[f"im_{h}_s0"])
        sd = max(float(a.std(ddof=1)) if a.size > 1 else 0.0, fit_sd) / math.sqrt(a.size)
        out[f"amplitude_V_{h}"] = Estimate(float(a.mean()), sd, "V")
        out[f"phase_rad_{h}"] = Estimate(math.nan, math.nan, "rad", False, NO_CLOCK)
        h += 1
    return out
