"""The range of validity a certificate states, and its Bode plot drawn within it.

The plan bounds every statement: the crank frequencies of the kept steps and the amplitudes of the
inertial force M (2 pi f)^2 r they produced (M the moving mass, r the crank radius).  The model's
validity is the structure the result states (``assumptions.structure``): Eq. 9 with a stiff coupling
and the softest coupling the plan could not tell from a stiff one, or Eq. 8.  The Bode plot (SVG,
embedded in the certificate) shows the measured S_dyn with U (k = 2) and the model with its k = 2
band from the stated covariance, only between the lowest and the highest frequency of the plan.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from station.certificate.present import plain, unit_text


def force_amplitudes(f_hz: Sequence[float], radius_m: Sequence[float], mass_kg: float) -> list[float]:
    """Amplitude of the inertial force M (2 pi f)^2 r at each step, N."""
    return [mass_kg * (2 * math.pi * f) ** 2 * r for f, r in zip(f_hz, radius_m, strict=True)]


def model_validity(structure: Mapping[str, Any] | None) -> str:
    """One sentence: the model the values rest on and what this plan supports of it."""
    if not structure:
        return "The model structure is not stated with this result."
    eq = structure.get("equation", "")
    c = structure.get("coupling") or {}
    if eq == "Eq. 8":
        return ("Model: Eq. 8 of the method (a finite coupling stiffness k_c and damping b_c between the transducer "
                "and the rig), determined by this plan.")
    if c.get("contradicted_by_the_data"):
        return ("Model: Eq. 9 of the method (stiff coupling), which the data contradict: the transducer's stiffness "
                "alone is not certified, only the series stiffness of transducer and coupling.")
    lo = c.get("k_c_lower_bound_N_per_m")
    ratio = c.get("k_c_lower_bound_over_k_s")
    if isinstance(lo, int | float):
        return (f"Model: Eq. 9 of the method (stiff coupling). The plan supports it for a coupling stiffness "
                f"k_c > {plain(lo, 2)} N/m ({plain(ratio, 2)} times the series stiffness): a softer coupling would "
                "have shown in the data; a stiffer one cannot be told from a stiff one.")
    return "Model: Eq. 9 of the method (stiff coupling); the plan's sensitivity to a coupling is not stated."


def validity(f_hz: Sequence[float], radius_m: Sequence[float], mass_kg: float,
             structure: Mapping[str, Any] | None) -> dict[str, Any]:
    """The certificate's ``validity``: frequency and force-amplitude ranges, and the model sentence."""
    forces = force_amplitudes(f_hz, radius_m, mass_kg)
    f_lo, f_hi = float(min(f_hz)), float(max(f_hz))
    F_lo, F_hi = float(min(forces)), float(max(forces))
    return {"f_min_hz": f_lo, "f_max_hz": f_hi, "force_min_N": F_lo, "force_max_N": F_hi,
            "model": model_validity(structure),
            "text": (f"The results are valid for sinusoidal forces of frequency {plain(f_lo, 4)} Hz to "
                     f"{plain(f_hi, 4)} Hz and amplitude {plain(F_lo, 3)} N to {plain(F_hi, 3)} N with a moving "
                     "mass of "
                     f"{plain(mass_kg, 5)} kg, as calibrated; no statement is made outside these ranges, and "
                     "S_dyn(f) is stated at the measured frequencies only.")}


def bode_svg(points: Sequence[Mapping[str, Any]], unit: str, model: tuple[np.ndarray, np.ndarray, np.ndarray | None,
             np.ndarray, np.ndarray | None] | None, k: float) -> str:
    """The certificate's Bode plot as SVG text: points (the content's ``response``: f_hz, magnitude,
    U_magnitude, phase_deg, U_phase_deg); model: (f, |S|, u or None, phase rad, u or None) on a grid
    within the plan's range, or None."""
    from matplotlib.backends.backend_svg import FigureCanvasSVG
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.7, 4.0))
    FigureCanvasSVG(fig)
    ax_m, ax_p = fig.subplots(2, 1, sharex=True)
    fig.subplots_adjust(left=0.13, right=0.98, top=0.97, bottom=0.12, hspace=0.08)
    f = np.array([p["f_hz"] for p in points])
    mag = np.array([p["magnitude"] for p in points])
    ph = np.array([p["phase_deg"] for p in points])
    if model is not None:
        ff, m_mag, m_u, m_ph, m_uph = model
        m_deg = np.degrees(m_ph)
        ph = np.interp(f, ff, m_deg) + ((ph - np.interp(f, ff, m_deg) + 180.0) % 360.0 - 180.0)
        ax_m.plot(ff, m_mag, "C1", lw=1, label="model")
        ax_p.plot(ff, m_deg, "C1", lw=1)
        if m_u is not None and m_uph is not None:
            ax_m.fill_between(ff, m_mag - k * m_u, m_mag + k * m_u, color="C1", alpha=0.25, lw=0,
                              label=f"model, U (k = {k:g})")
            ax_p.fill_between(ff, m_deg - np.degrees(k * m_uph), m_deg + np.degrees(k * m_uph), color="C1",
                              alpha=0.25, lw=0)
    ax_m.errorbar(f, mag, yerr=[p["U_magnitude"] for p in points], fmt="o", ms=3, color="C0", capsize=2,
                  label=f"measured, U (k = {k:g})")
    ax_p.errorbar(f, ph, yerr=[p["U_phase_deg"] for p in points], fmt="o", ms=3, color="C0", capsize=2)
    ax_m.set(ylabel=f"|S_dyn| ({unit_text(unit)})", xscale="log")
    ax_p.set(ylabel="phase (°)", xlabel="frequency (Hz)", xscale="log", xlim=(0.95 * f.min(), 1.05 * f.max()))
    ax_m.legend(fontsize=7, loc="upper left")
    for ax in (ax_m, ax_p):
        ax.grid(True, which="both", alpha=0.3)
        ax.tick_params(labelsize=7)
        ax.yaxis.label.set_fontsize(8)
    ax_p.xaxis.label.set_fontsize(8)
    buf = io.StringIO()
    fig.savefig(buf, format="svg", metadata={"Date": None})
    return buf.getvalue()
