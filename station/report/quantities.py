"""Dynamic sensitivity with uncertainties, and the formatting of values with uncertainties.

Dynamic sensitivity (V/N): S_dyn(f) = -H(f) / M, the force signal per inertial force M a of the
moving masses (M = m_e + m_l, a the frame acceleration); its static limit is the sensitivity S, its
magnitude rises towards the resonance sqrt(k_f/M)/(2 pi) and its phase falls.  Measured points take
their uncertainty from the 2x2 covariance of (Re H, Im H) (delta method); the model curve takes its
from the parameter covariance (J C J^T).  The measured points add the uncertainty of M = m_e + m_l
in quadrature (relative, |S_dyn| u(M)/M) when it is given.  u is the standard uncertainty (k = 1),
U = 2 u the expanded one (k = 2; these points rest on thousands of samples each).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from station.report.data import ModelCurve

FloatArray = NDArray[np.float64]
COVERAGE_K = 2.0


def polar_uncertainty(z: NDArray[np.complex128], cov: FloatArray) -> tuple[FloatArray, FloatArray,
                                                                          FloatArray, FloatArray]:
    """(|z|, u(|z|), angle(z) in rad, u(angle) in rad) from cov (n, 2, 2) of (Re z, Im z)."""
    z = np.asarray(z, complex)
    mag = np.abs(z)
    g_mag = np.stack([z.real, z.imag], axis=-1) / mag[:, None]
    g_ph = np.stack([-z.imag, z.real], axis=-1) / (mag**2)[:, None]
    u_mag = np.sqrt(np.einsum("ni,nij,nj->n", g_mag, cov, g_mag))
    u_ph = np.sqrt(np.einsum("ni,nij,nj->n", g_ph, cov, g_ph))
    return mag, u_mag, np.angle(z), u_ph


def measured_sensitivity(H: NDArray[np.complex128], cov: FloatArray, mass_kg: float, mass_std_kg: float = 0.0
                         ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """|S_dyn| (V/N), u (V/N), phase (rad), u (rad) of the measured points; mass_std_kg: u(M)."""
    mag, u_mag, ph, u_ph = polar_uncertainty(np.asarray(-np.asarray(H, complex) / mass_kg, dtype=np.complex128),
                                             np.asarray(cov, float) / mass_kg**2)
    return mag, np.hypot(u_mag, mag * mass_std_kg / mass_kg), ph, u_ph


def model_sensitivity(curve: ModelCurve, f_hz: ArrayLike) -> tuple[FloatArray, FloatArray | None,
                                                                   FloatArray, FloatArray | None]:
    """|S_dyn| (V/N), u or None, unwrapped phase (rad), u or None of the model at f_hz."""
    f = np.atleast_1d(np.asarray(f_hz, float))
    M = curve.model.M
    S = -curve.model.response(curve.theta, f) / M
    phase = np.unwrap(np.angle(S))
    if curve.cov is None:
        return np.abs(S), None, phase, None
    J = -curve.model.jacobian(curve.theta, f) / M  # (n, p) complex
    g_mag = (np.conj(S)[:, None] * J).real / np.abs(S)[:, None]
    g_ph = (J / S[:, None]).imag
    u_mag = np.sqrt(np.einsum("ni,ij,nj->n", g_mag, curve.cov, g_mag))
    u_ph = np.sqrt(np.einsum("ni,ij,nj->n", g_ph, curve.cov, g_ph))
    return np.abs(S), u_mag, phase, u_ph


def _finite(x: float | None) -> bool:
    return x is not None and math.isfinite(x)


def fmt_value(value: float | None, u: float | None = None) -> str:
    """The value rounded to the second significant digit of its uncertainty (7 digits without one);
    plain notation for 1e-3 <= |value| < 1e5, else scientific."""
    if not _finite(value):
        return "n/a"
    assert value is not None
    if not _finite(u) or not u:
        return f"{value:.7g}"
    assert u is not None
    q = math.floor(math.log10(abs(u))) - 1  # decimal place of u's second significant digit
    e = math.floor(math.log10(abs(value))) if value else q
    if -3 <= e < 5:
        return f"{value:.{max(0, -q)}f}"
    return f"{value:.{max(0, e - q)}e}"


def fmt_unc(u: float | None) -> str:
    """An uncertainty to two significant digits."""
    if not _finite(u):
        return "n/a"
    assert u is not None
    return f"{u:.2g}" if 1e-3 <= abs(u) < 1e5 or u == 0 else f"{u:.1e}"


def fmt_rel(value: float | None, u: float | None) -> str:
    """Relative uncertainty in %, two significant digits."""
    if not (_finite(value) and _finite(u)) or not value:
        return "n/a"
    assert value is not None and u is not None
    return f"{100 * abs(u / value):.2g}"


def range_text(rng: Sequence[float | None]) -> str:
    """'[lo, hi]' of a conditional range, 'from lo up (unbounded)' when hi is None."""
    lo, hi = rng
    if hi is None:
        return f"{fmt_value(lo)} and up (unbounded)"
    return f"[{fmt_value(lo)}, {fmt_value(hi)}]"


def structure_sentence(statement: dict) -> str:
    """One sentence for a result's ``assumptions.structure``: the model it rests on, the displacement
    chain, and the coupling this plan can or cannot exclude."""
    out = [str(statement.get("model", "?"))]
    ch = statement.get("displacement_chain") or {}
    if ch.get("response") == "resonance":
        out.append(f"displacement sensor resonance {ch.get('resonance_hz')} Hz (u {ch.get('resonance_std_hz')} Hz), "
                   f"damping {ch.get('damping')} (u {ch.get('damping_std')}): H(f) corrected for it")
    else:
        out.append("displacement chain taken as flat")
    c = statement.get("coupling") or {}
    if c.get("contradicted_by_the_data"):
        out.append("the data contradict a stiff coupling (coupling_suspected): k_f alone not determined")
    elif c.get("k_c_lower_bound_over_k_s") is not None:
        out.append(f"this plan cannot tell a coupling k_c >= {c['k_c_lower_bound_over_k_s']:.3g} k_s from a stiff one; "
                   f"k_f alone in {range_text(c.get('k_f_alone_range_N_per_m') or [None, None])} N/m")
    return "; ".join(out)
