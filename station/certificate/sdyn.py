"""The dynamic sensitivity S_dyn(f) = -H(f)/M of the certificate with every source of the budget.

The measured points (the stored H(f) of the steps, corrected for a stated displacement-sensor
resonance as the fit was) carry, per frequency and independent of one another's noise, the same
sources the parameters' budget propagates (``station.ident.fd.budget``), as standard uncertainties
of the magnitude (relative) and of the phase (rad):

* noise: the sine fits' covariance of (Re H, Im H) (delta method);
* chain_gain: the gain ratio of the chains (gain_rel_std) and its flatness (flatness_rel_std);
* chain_phase: the phase offset (phase_offset_std_deg) and the per-frequency phase (phase_std_deg);
* chain_delay: the channels' time skew, phase 2 pi f u(tau);
* chain_resonance: the stated displacement-sensor resonance, d ln H_s / d f_r u(f_r) and / d p u(p)
  (real part: magnitude, imaginary part: phase);
* masses: u(M)/M with u(M) = sqrt(u(m_e)^2 + u(m_l)^2) on the magnitude (0 for an end mass the
  result is conditional on, as in the budget);
* conditioner_gain: the reference conditioner's gain and excitation when S is the transducer's.

Correlated sources (a gain or phase offset common to all frequencies) are stated per point; the
sources are independent, so u is their root sum of squares.  Magnitudes are in the item's unit.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from station.config import MeasurementChain
from station.ident.fd.budget import resonance_vectors
from station.ident.response.frf import FrequencyResponse
from station.ident.structure import chain_corrected
from station.report.quantities import polar_uncertainty

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SdynPoints:
    """f_hz (n,); magnitude in the item's unit and phase in rad; mag_terms / phase_terms: per
    source (n,) standard uncertainties (magnitude in the item's unit, phase in rad)."""

    f_hz: FloatArray
    magnitude: FloatArray
    phase_rad: FloatArray
    mag_terms: dict[str, FloatArray]
    phase_terms: dict[str, FloatArray]

    @property
    def u_magnitude(self) -> FloatArray:
        return np.sqrt(sum(t**2 for t in self.mag_terms.values()))

    @property
    def u_phase_rad(self) -> FloatArray:
        return np.sqrt(sum(t**2 for t in self.phase_terms.values()))


def sdyn_points(f_hz: FloatArray, H: NDArray[np.complex128], cov: FloatArray, mass_kg: float,
                mass_std_kg: float, chain: MeasurementChain, scale: float = 1.0,
                conditioner_rel_std: float = 0.0) -> SdynPoints:
    """S_dyn at the measured steps with every source (module docstring); scale: the item's unit per
    V/N (``station.certificate.item``)."""
    f = np.asarray(f_hz, float)
    frf = chain_corrected(FrequencyResponse(f, np.asarray(H, complex), np.asarray(cov, float), np.zeros(f.size),
                                            np.zeros(f.size)), chain)
    S = -frf.H / mass_kg * scale
    mag, u_noise, ph, u_ph_noise = polar_uncertainty(np.asarray(S, np.complex128), frf.cov * (scale / mass_kg) ** 2)
    ones = np.ones(f.size)
    rel_res = np.zeros(f.size)
    ph_res = np.zeros(f.size)
    for v, s in resonance_vectors(ones.astype(complex), f, chain):  # d ln H per unit, times u
        rel_res = np.hypot(rel_res, (v * s).real)
        ph_res = np.hypot(ph_res, (v * s).imag)
    mag_terms = {"noise": u_noise,
                 "chain_gain": mag * float(np.hypot(chain.gain_rel_std, chain.flatness_rel_std)),
                 "chain_resonance": mag * rel_res,
                 "masses": mag * (mass_std_kg / mass_kg),
                 "conditioner_gain": mag * conditioner_rel_std}
    phase_terms = {"noise": u_ph_noise,
                   "chain_phase": ones * float(np.deg2rad(np.hypot(chain.phase_offset_std_deg, chain.phase_std_deg))),
                   "chain_delay": 2 * np.pi * f * chain.delay_std_s,
                   "chain_resonance": ph_res}
    return SdynPoints(f, mag, ph, mag_terms, phase_terms)


def chain_of(assumptions: Mapping[str, Any]) -> MeasurementChain:
    """The measurement chain a result stated (``assumptions.measurement_chain``), defaults otherwise."""
    raw = assumptions.get("measurement_chain")
    return MeasurementChain.model_validate(raw if isinstance(raw, Mapping) else {})
