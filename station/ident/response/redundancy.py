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
* **The static force against the weight of the stated masses.**  The force channel's mean over a
  step is the gravity preload, -S (m_l + m_e) g (the frame's acceleration averages out), so the
  means less the conditioner's stated offset, divided by the identified S, are the weight of the
  moving masses.  S rests on the stated masses, so the masses cancel from the comparison: what it
  checks is the acceleration scale S rests on (the displacement sensor's calibration, the crank
  radius) against gravity, and the force channel's zero (the conditioner's stated offset, a zero
  drift).  The plan allows it for this station's own recordings of a DC-coupled chain (a bridge,
  ``conditioner.gain_unit`` V/V): not a charge amplifier's (V/pC), not an imported file (whose zero
  is unknown).  Standard gravity is used, its relative standard uncertainty against a local value
  (``G_REL_STD``: +-0.27 % between equator and poles, rectangular) a default no certificate supports.

Every default the comparison uses that no certificate supports is named in the finding.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from station.ident.inputs import IdentInputs
from station.ident.response.sinefit import SineFit, estimate_frequency
from station.ident.result import Check, Estimate
from station.kept import Kept, content_key
from station.vocabulary import Severity

Z_FINDING = 3.0  # combined standard uncertainties beyond which a disagreement is a finding
CLOCK_SAMPLES = 4000  # force samples per step the clock comparison fits (at most)
Z_CLOCK = 5.0  # the clock comparison is a test over every step: a stricter line against false alarms
G_STANDARD = 9.80665  # m/s^2
G_REL_STD = 0.0027 / math.sqrt(3)  # local gravity against standard gravity (equator to poles), relative


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
    return Check("displacement_vs_radius", Severity.WARNING, None,
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


_force_frequencies: Kept[tuple[float, float]] = Kept(256, lambda v: v)


def _force_frequency(t: np.ndarray, force: np.ndarray, f0_hz: float, n_harmonics: int) -> tuple[float, float]:
    """(f, f_std) of the force samples (``sinefit.estimate_frequency`` from f0_hz), kept by the
    content of the samples and settings (``kept``): the same step checked again is not fitted again."""
    key = content_key(t, force, settings=(float(f0_hz), int(n_harmonics)))
    return _force_frequencies.get(key, lambda: estimate_frequency(t, force, f0_hz, n_harmonics=n_harmonics)[:2])


def clock_cache_clear() -> None:
    """Drop the kept force frequencies."""
    _force_frequencies.clear()


def clock_check(steps: dict[int, tuple[np.ndarray, np.ndarray, SineFit]], n_harmonics: int) -> Check | None:
    """Both channels' frequencies per step (``steps``: index -> (t s, force V, displacement fit));
    a warning when the force's differs from the displacement's beyond ``Z_CLOCK`` over the steps."""
    rel, var = [], []
    for t, force, fx in steps.values():
        k = max(1, t.size // CLOCK_SAMPLES)  # a subsample: its frequency is precise enough for a few ppm
        try:
            fu, fu_std = _force_frequency(t[::k], force[::k], fx.frequency_hz, n_harmonics)
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
    return Check("clock_skew", Severity.WARNING, None,
                 f"the force channel runs at {1e6 * eps:+.3g} ppm of the displacement channel's frequency "
                 f"(standard uncertainty {1e6 * u:.2g} ppm, z {z:+.3g}, over {len(rel)} steps): the two converters' "
                 "clocks disagree, which shows as a force phase that grows with time within each step and biases "
                 "the damping b_f (and S at high frequencies); check the DAQ bridge's sample clocks (one clock for "
                 "both converters)",
                 {"relative": eps, "std": u, "z": z, "per_step": rel})


def _stated_zero_V(config: object) -> float | None:
    """The force channel's stated zero (the conditioner's offset, V) where the plan allows the static
    comparison (module docstring), else None."""
    if not isinstance(config, dict) or config.get("format") == "sinecal-csv":
        return None
    cond = config.get("conditioner")
    cond = cond if isinstance(cond, dict) else {}
    if cond.get("gain_unit", "V/V") != "V/V":
        return None
    off = cond.get("offset_V", 0.0)
    return float(off) if isinstance(off, int | float) and not isinstance(off, bool) else None


def static_check(offsets: tuple[tuple[float, float, float], ...], S: Estimate, mass_kg: float,
                 config: object, displacement_off: bool) -> Check | None:
    """The static force against the weight of the stated masses (module docstring).

    offsets: the force channel's mean per step (window centre s, V, standard uncertainty V);
    S: the identified sensitivity in V/N with its budget; mass_kg: m_l + m_e as stated;
    displacement_off: the displacement amplitude disagreed with the crank radius (its finding).
    A warning naming the standard to check beyond ``Z_FINDING`` combined standard uncertainties, else None."""
    zero = _stated_zero_V(config)
    if zero is None or not offsets or not S.identifiable or S.value is None or S.std is None:
        return None
    if not (math.isfinite(S.value) and S.value != 0 and math.isfinite(S.std) and mass_kg > 0):
        return None
    v = np.array([o for _, o, _ in offsets])
    s = np.array([max(u, 1e-12) for _, _, u in offsets])
    w = 1 / s**2
    mean = float(np.sum(w * v) / np.sum(w))
    u_mean = math.sqrt(1 / float(np.sum(w)))
    dof = v.size - 1
    chi2 = float(np.sum(w * (v - mean) ** 2))
    drifts = dof > 0 and chi2 > dof + 5 * math.sqrt(2 * dof)  # the means move from step to step
    if dof > 0 and chi2 > dof:
        u_mean *= math.sqrt(chi2 / dof)
    weight = mass_kg * G_STANDARD
    q = -(mean - zero) / (S.value * weight)
    u_s = abs(S.std / S.value)  # S's budget holds the masses' share, which cancels here: conservative
    u = math.sqrt(u_s**2 + (u_mean / abs(S.value * weight)) ** 2 + G_REL_STD**2)
    z = (q - 1) / u
    if abs(z) <= Z_FINDING:
        return None
    which = ("the force channel's mean moves from step to step: check the force channel's zero (the "
             "conditioner's offset, a zero drift) first, then the displacement sensor's calibration" if drifts else
             "the displacement amplitude disagrees with the crank radius too: check the displacement sensor's "
             "calibration (the acceleration S rests on) first, then the force channel's zero" if displacement_off
             else "check the force channel's zero (the conditioner's stated offset) and the displacement sensor's "
             "calibration (the acceleration S rests on); then the local gravity")
    return Check("static_force_vs_weight", Severity.WARNING, None,
                 f"the static force (the force channel's mean {mean:.6g} V less the stated zero {zero:.6g} V, over "
                 f"the identified S) is {q:.6g} times the weight of the stated masses ({mass_kg:.6g} kg x "
                 f"{G_STANDARD} m/s^2) (z {z:+.3g}; combined standard uncertainty {u:.2g}: S's budget, the steps' "
                 f"means, local gravity u = {G_REL_STD:.2g} (relative; standard gravity used, a default no "
                 f"certificate supports)): the static and the dynamic force scales disagree; {which}",
                 {"ratio": q, "std": u, "z": z, "mean_V": mean, "mean_std_V": u_mean, "zero_V": zero,
                  "weight_N": weight, "gravity_rel_std": G_REL_STD, "zero_drifts": bool(drifts)})
