"""Redundant measurements check each other, within their stated uncertainties.

* **Displacement against the crank radius.**  The measured displacement amplitude (the sine fit's
  fundamental, corrected for a stated displacement-sensor resonance) is the crank radius.  Per
  distinct radius r the steps' ratios A / r are averaged (noise weights), each radius carries its
  setting's standard uncertainty u(r) / r (``rig.crank_radius_std_m``), and the radii's weighted mean
  deviation is compared with its combined standard uncertainty, the displacement chain's gain term
  (``identification.chain.gain_rel_std``) added.  Beyond 3 standard uncertainties it is a finding
  that names the standard to check: the same ratio at every radius is a gain (the displacement
  sensor's calibration), a deviation that shrinks with the radius is the radius setting.
* **One clock for both converters.**  Each step's frequency is measured on the displacement channel
  and, separately, on the force channel.  Both converters sample the same crank motion, so the two
  frequencies agree within their standard uncertainties unless the converters' clocks differ (a
  clock skew shows as a force phase that grows with time within a step, and from step to step).

Every default the comparison uses that no certificate supports is named in the finding.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from station.ident.inputs import IdentInputs
from station.ident.response.sinefit import SineFit, estimate_frequency
from station.ident.result import Check

Z_FINDING = 3.0  # combined standard uncertainties beyond which a disagreement is a finding
CLOCK_SAMPLES = 4000  # force samples per step the clock comparison fits (at most)
Z_CLOCK = 5.0  # the clock comparison is a test over every step: a stricter line against false alarms


def _amplitude_std(fit: SineFit) -> float:
    return float(math.sqrt(max(np.trace(fit.phasor_cov) / 2, 0.0)))


def _sensor_gain(inputs: IdentInputs, f_hz: float) -> float:
    """|H_s| of the stated displacement-sensor resonance at f_hz (1 for a flat chain)."""
    res = inputs.chain.displacement_resonance
    if res is None:
        return 1.0
    wr, w = 2 * math.pi * res.resonance_hz, 2 * math.pi * f_hz
    return float(abs(wr**2 / (wr**2 - w**2 + 2j * res.damping * wr * w)))


def radius_check(fits: dict[int, SineFit], radii: dict[int, float], inputs: IdentInputs) -> Check | None:
    """The displacement amplitude against the crank radius over the steps ``fits`` (module docstring);
    a warning when they disagree beyond ``Z_FINDING`` combined standard uncertainties, else None."""
    groups: dict[float, list[tuple[float, float]]] = {}
    for i, fit in fits.items():
        r = radii.get(i)
        if r is None or not r > 0:
            continue
        a = abs(fit.phasor) / _sensor_gain(inputs, fit.frequency_hz)
        groups.setdefault(float(r), []).append((a / r, max(_amplitude_std(fit) / r, 1e-15)))
    if not groups:
        return None
    u_r = inputs.crank_radius_std_m
    dev, var, per_radius = [], [], []
    for r, rows in sorted(groups.items()):
        w = np.array([1 / s**2 for _, s in rows])
        mean = float(np.sum(w * [q for q, _ in rows]) / np.sum(w))
        v = 1 / float(np.sum(w)) + (u_r / r) ** 2
        dev.append(mean - 1)
        var.append(v)
        per_radius.append({"radius_m": r, "ratio": mean, "std": math.sqrt(v)})
    wts = 1 / np.array(var)
    d = float(np.sum(wts * dev) / np.sum(wts))
    u_gain = inputs.chain.gain_rel_std
    u = math.sqrt(1 / float(np.sum(wts)) + u_gain**2)
    z = d / u
    if abs(z) <= Z_FINDING:
        return None
    gain_like = _gain_not_radius(dev, var, [p["radius_m"] for p in per_radius])
    which = ("the same ratio at every radius: check the displacement sensor's calibration (its gain) first, "
             "then the crank radius" if gain_like is True else
             "the deviation shrinks with the radius: check the crank radius setting first, then the displacement "
             "sensor's calibration" if gain_like is False else
             "check the displacement sensor's calibration (its gain) and the crank radius setting")
    used = [x for x in inputs.defaults if x.startswith(("crank radius", "measurement chain gain"))]
    dflt = f"; defaults no certificate supports: {', '.join(used)}" if used else ""
    return Check("displacement_vs_radius", "warning", None,
                 f"the measured displacement amplitude is {1 + d:.6g} times the stated crank radius (z {z:+.3g}; "
                 f"combined standard uncertainty {u:.2g}: noise, crank radius u = {u_r:.3g} m, displacement "
                 f"chain gain u = {u_gain:.2g}{dflt}): the two standards disagree; {which}. S scales with the "
                 "displacement chain's gain",
                 {"ratio": 1 + d, "std": u, "z": z, "per_radius": per_radius, "crank_radius_std_m": u_r,
                  "gain_rel_std": u_gain})


def _gain_not_radius(dev: list[float], var: list[float], radii: list[float]) -> bool | None:
    """True: one relative deviation fits every radius (a gain); False: one absolute offset of the
    radius fits clearly better; None: one radius only, or neither is clearly better."""
    if len(radii) < 2:
        return None
    d, v, r = np.array(dev), np.array(var), np.array(radii)
    w = 1 / v
    g = float(np.sum(w * d) / np.sum(w))
    chi_gain = float(np.sum(w * (d - g) ** 2))
    x = 1 / r  # d = delta / r for a radius offset delta
    delta = float(np.sum(w * d * x) / np.sum(w * x * x))
    chi_offset = float(np.sum(w * (d - delta * x) ** 2))
    if chi_gain + 9 < chi_offset:
        return True
    if chi_offset + 9 < chi_gain:
        return False
    return None


def beside_clock_skew(checks: list[Check]) -> list[Check]:
    """With a clock skew found, the explanations of a misfit (a coupling, the misfit itself) name it
    beside them: a phase that grows with time misfits Eq. 9 as a coupling's does."""
    if not any(c.name == "clock_skew" for c in checks):
        return checks
    also = ("; or the converters' clock skew found in the same data (clock_skew): a force phase that grows with "
            "time misfits Eq. 9 too, so the misfit need not be a coupling")
    return [replace(c, message=c.message + also)
            if c.name in ("coupling_suspected", "coupling_not_excluded", "model_misfit") else c for c in checks]


def clock_check(steps: dict[int, tuple[np.ndarray, np.ndarray, SineFit]], n_harmonics: int) -> Check | None:
    """Both channels' frequencies per step (``steps``: index -> (t s, force V, displacement fit));
    a warning when the force's differs from the displacement's beyond ``Z_CLOCK`` over the steps."""
    rel, var = [], []
    for t, force, fx in steps.values():
        k = max(1, t.size // CLOCK_SAMPLES)  # a subsample: its frequency is precise enough for a few ppm
        try:
            fu, fu_std, _ = estimate_frequency(t[::k], force[::k], fx.frequency_hz, n_harmonics=n_harmonics)
        except (np.linalg.LinAlgError, ValueError, FloatingPointError):
            continue
        s2 = (fu_std**2 + fx.frequency_std_hz**2) / fx.frequency_hz**2
        if not (math.isfinite(fu) and s2 > 0 and math.isfinite(s2)):
            continue
        rel.append(fu / fx.frequency_hz - 1)
        var.append(s2)
    if len(rel) < 1:
        return None
    w = 1 / np.array(var)
    eps = float(np.sum(w * rel) / np.sum(w))
    u = math.sqrt(1 / float(np.sum(w)))
    z = eps / u
    if abs(z) <= Z_CLOCK:
        return None
    return Check("clock_skew", "warning", None,
                 f"the force channel runs at {1e6 * eps:+.3g} ppm of the displacement channel's frequency "
                 f"(standard uncertainty {1e6 * u:.2g} ppm, z {z:+.3g}, over {len(rel)} steps): the two converters' "
                 "clocks disagree, which shows as a force phase that grows with time within each step and biases "
                 "the damping b_f (and S at high frequencies); check the DAQ bridge's sample clocks (one clock for "
                 "both converters)",
                 {"relative": eps, "std": u, "z": z, "per_step": rel})
