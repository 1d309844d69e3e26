"""GUM uncertainty budget of the frequency-domain estimate (sensitivity coefficients, GUM 5.1.2).

The weighted least-squares estimate theta^ = argmin sum_i |W_i (H_model(f_i; theta, m) - H_i)|^2
responds to a small systematic change dH of the data and dm of a mass, to first order, as

    d theta = P (dH - dH_model/dm dm),   P = (J_w^T J_w)^-1 J_w^T W

(J_w the whitened Jacobian, W the whiteners; stacked real and imaginary parts).  Each source below
is a vector (correlated across frequencies) or a set of per-frequency vectors (independent); its
standard uncertainty in theta is the root sum of squares of P v sigma.  Sources:

* noise: the estimate's own covariance (Gauss-Markov, Birge-inflated when chi^2/dof says so);
* chain_gain: gain ratio of the chains, dH = H g (correlated) and flatness dH_i = H_i g_i;
* chain_phase: dH = j H phi (correlated offset) and dH_i = j H_i phi_i (independent);
* chain_delay: dH_i = j 2 pi f_i tau H_i, one tau for all frequencies;
* chain_resonance: the stated displacement-sensor resonance (f_r, p) that H was corrected for,
  dH = H d ln H_s/d f_r u(f_r) and H d ln H_s/d p u(p), each correlated (0 for a flat chain);
* end_mass, load_mass: d theta = -P dH_model/dm u(m) (the model's own mass dependence);
* radius: 0 -- the frame motion is the measured displacement, the stated crank radius enters no
  estimate (it is only checked against the measured amplitude).
The combined standard uncertainty is the root sum of squares (sources independent).

Degrees of freedom (GUM G.4): the Type B sources are taken as exactly known (infinite); the noise
term has the fit's residual degrees of freedom 2 n_f - p when its covariance was scaled by chi^2/dof
(Birge: the scale is then estimated from those few residuals), and is otherwise the sine fits' own,
each resting on thousands of samples (infinite).  ``to_dict`` stores them per parameter as
``dof: {source: nu}`` (only the finite ones); ``station.ident.coverage`` turns them into the
effective degrees of freedom (Welch-Satterthwaite) and k.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from station.config import MeasurementChain
from station.ident.inputs import IdentInputs
from station.ident.models import Model, make_model
from station.ident.response.frf import FrequencyResponse, whiteners

FloatArray = NDArray[np.float64]
SOURCES = ("noise", "chain_gain", "chain_phase", "chain_delay", "chain_resonance", "end_mass", "load_mass",
           "radius")


@dataclass(frozen=True)
class Budget:
    """covs[source]: covariance (n, n) of theta from that source (zero rows/columns for held
    parameters); None for a source not propagated (an assumed end mass: the result is conditional
    on it).  free: the parameters estimated; names and units per parameter."""

    names: tuple[str, ...]
    units: tuple[str, ...]
    covs: dict[str, FloatArray | None]
    free: NDArray[np.bool_]
    dof: dict[str, float] = field(default_factory=dict)

    @property
    def cov(self) -> FloatArray:
        """Combined covariance (sources independent)."""
        return np.asarray(sum(c for c in self.covs.values() if c is not None))

    @property
    def combined(self) -> FloatArray:
        """Combined standard uncertainty per parameter, NaN where held."""
        return np.where(self.free, np.sqrt(np.clip(np.diag(self.cov), 0, None)), np.nan)

    def std_of(self, grad: FloatArray, invariant: tuple[str, ...] = ()) -> dict[str, float | None]:
        """Standard uncertainty per source and combined of a derived quantity with gradient grad;
        sources in ``invariant`` do not change it (0; e.g. the masses for S M)."""
        out: dict[str, float | None] = {}
        for s, c in self.covs.items():
            out[s] = 0.0 if s in invariant else None if c is None else float(np.sqrt(max(float(grad @ c @ grad),
                                                                                          0.0)))
        out["combined"] = float(np.sqrt(sum(v * v for v in out.values() if v is not None)))
        return out

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for i, (n, u) in enumerate(zip(self.names, self.units, strict=True)):
            if not self.free[i]:
                continue
            c = {s: (None if v is None else float(np.sqrt(max(v[i, i], 0.0)))) for s, v in self.covs.items()}
            out[n] = {"contributions": c, "combined": float(self.combined[i]), "unit": u}
            if self.dof:
                out[n]["dof"] = dict(self.dof)
        return out


def resonance_vectors(H: NDArray[np.complex128], f_hz: FloatArray,
                      chain: MeasurementChain) -> list[tuple[NDArray[np.complex128], float]]:
    """The budget's chain_resonance source: dH = H d ln H_s / d q times u(q), q = f_r and p
    (correlated across frequencies); empty for a flat chain."""
    res = chain.displacement_resonance
    if res is None:
        return []
    f = np.asarray(f_hz, float)
    r = f / res.resonance_hz
    den = 1.0 - r * r + 2j * res.damping * r
    dln_dfr = (-2.0 * r * r + 2j * res.damping * r) / den / res.resonance_hz  # d ln H_s / d f_r
    dln_dp = -2j * r / den
    return [(H * dln_dfr, chain.resonance_std_hz), (H * dln_dp, float(chain.displacement_damping_std))]


def _stack(dH: NDArray[np.complex128]) -> FloatArray:
    return np.column_stack([dH.real, dH.imag]).ravel()


def _projector(model: Model, theta: FloatArray, frf: FrequencyResponse, free: NDArray[np.bool_]) -> FloatArray:
    """P (n_free, 2 n_f) mapping a stacked dH of the data to d theta of the free parameters."""
    W = whiteners(frf.cov)
    Wb = np.zeros((2 * W.shape[0], 2 * W.shape[0]))
    for i, w in enumerate(W):
        Wb[2 * i:2 * i + 2, 2 * i:2 * i + 2] = w
    Jc = model.jacobian(theta, frf.f_hz)[:, free]
    J = np.stack([Jc.real, Jc.imag], axis=1).reshape(-1, int(free.sum()))
    Jw = Wb @ J
    return np.asarray(np.linalg.pinv(Jw) @ Wb, dtype=np.float64)


def _mass_derivative(model: Model, theta: FloatArray, f_hz: FloatArray,
                     which: str) -> NDArray[np.complex128]:
    """dH_model/dm (per kg) by central differences, m_e or m_l."""
    h = 1e-6 * max(model.m_e + model.m_l, 1e-3)
    mk: Callable[[float], Model] = (
        (lambda d: make_model(model.key, model.m_e + d, model.m_l)) if which == "end_mass"
        else (lambda d: make_model(model.key, model.m_e, model.m_l + d)))
    return (mk(h).response(theta, f_hz) - mk(-h).response(theta, f_hz)) / (2 * h)


def uncertainty_budget(model: Model, theta: FloatArray, noise_cov: FloatArray, frf: FrequencyResponse,
                       free: NDArray[np.bool_], inputs: IdentInputs, noise_dof: float | None = None) -> Budget:
    """The budget of the free parameters of ``theta`` (held ones get zero rows and columns);
    noise_dof: the noise term's degrees of freedom when finite (module docstring), else None."""
    n = theta.size
    idx = np.nonzero(free)[0]
    P = _projector(model, theta, frf, free)
    H, f = frf.H, frf.f_hz
    ch = inputs.chain

    def spread(vectors: list[tuple[NDArray[np.complex128], float]]) -> FloatArray:
        cov = np.zeros((n, n))
        for v, s in vectors:
            d = np.zeros(n)
            d[idx] = P @ _stack(v) * s
            cov += np.outer(d, d)
        return cov

    def single(k: int, z: NDArray[np.complex128]) -> NDArray[np.complex128]:
        e = np.zeros_like(z)
        e[k] = z[k]
        return e

    phi = np.deg2rad(ch.phase_std_deg)
    covs: dict[str, FloatArray | None] = {}
    noise = np.zeros((n, n))
    noise[np.ix_(idx, idx)] = noise_cov[np.ix_(idx, idx)]
    covs["noise"] = noise
    covs["chain_gain"] = spread([(H, ch.gain_rel_std)]
                                + [(single(k, H), ch.flatness_rel_std) for k in range(H.size)])
    covs["chain_phase"] = spread([(1j * H, np.deg2rad(ch.phase_offset_std_deg))]
                                 + [(single(k, 1j * H), phi) for k in range(H.size)])
    covs["chain_delay"] = spread([(2j * np.pi * f * H, ch.delay_std_s)])
    covs["chain_resonance"] = spread(resonance_vectors(H, f, ch))
    for name, m in (("end_mass", inputs.end_mass), ("load_mass", inputs.load_mass)):
        covs[name] = None if m.std is None else spread(
            [(_mass_derivative(model, theta, f, name), float(m.std))])
    covs["radius"] = np.zeros((n, n))
    return Budget(tuple(model.names), tuple(model.units), covs, np.asarray(free, bool),
                  {} if noise_dof is None else {"noise": float(noise_dof)})
