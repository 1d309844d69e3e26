"""GUM Supplement 1 Monte Carlo propagation of the frequency-domain estimate, a check of the linear
budget (``station.ident.fd.budget``).

Each trial draws every source the budget propagates from its stated distribution (normal) and
refits the model by the same weighted Levenberg-Marquardt (``frf.fit_frf``, started at the estimate):

* noise: H_i + L_i z_i, L_i the Cholesky factor of the point's covariance (scaled by chi^2/dof when
  the fit was; then the scale itself is drawn, chi^2_nu / nu);
* chain_gain: H (1 + g + g_i); chain_phase: H exp(j (phi + phi_i)); chain_delay: H exp(j 2 pi f tau);
* chain_resonance: H H_s(f_r, p) / H_s(f_r', p') (the correction redone with drawn f_r', p');
* end_mass, load_mass: the model's masses drawn (only when the budget propagates them).

Output per free parameter: the mean, the standard deviation and the probabilistically symmetric 95 %
coverage interval of the trials beside the linear u and y +- k u; ``agrees`` applies GUM S1 section
8 with the numerical tolerance delta of one significant digit of u.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from station.ident.inputs import IdentInputs
from station.ident.models import make_model
from station.ident.response.frf import FrequencyResponse, fit_frf
from station.jsonvalue import JsonValue

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class McParameter:
    """One parameter: the estimate y, linear u and k; Monte Carlo mean, std and 95 % interval."""

    name: str
    unit: str
    y: float
    u_linear: float
    k: float
    mean: float
    u_mc: float
    low: float
    high: float

    @property
    def delta(self) -> float:
        """GUM S1 7.9.2 numerical tolerance: half a unit of u's one significant digit."""
        return 0.5 * 10 ** math.floor(math.log10(self.u_linear)) if self.u_linear > 0 else 0.0

    @property
    def d_low(self) -> float:
        return abs(self.y - self.k * self.u_linear - self.low)

    @property
    def d_high(self) -> float:
        return abs(self.y + self.k * self.u_linear - self.high)

    @property
    def agrees(self) -> bool:
        """GUM S1 8.2: both ends of y +- k u within delta of the Monte Carlo interval's."""
        return self.d_low <= self.delta and self.d_high <= self.delta

    def to_dict(self) -> dict[str, JsonValue]:
        return {"name": self.name, "unit": self.unit, "y": self.y, "u_linear": self.u_linear, "k": self.k,
                "mean": self.mean, "u_mc": self.u_mc, "interval": [self.low, self.high], "d_low": self.d_low,
                "d_high": self.d_high, "delta": self.delta, "agrees": self.agrees}


@dataclass(frozen=True)
class MonteCarloCheck:
    trials: int
    seed: int
    sources: tuple[str, ...]
    parameters: tuple[McParameter, ...]

    @property
    def agrees(self) -> bool:
        return all(p.agrees for p in self.parameters)

    def to_dict(self) -> dict[str, JsonValue]:
        return {"trials": self.trials, "seed": self.seed, "sources": list(self.sources),
                "parameters": [p.to_dict() for p in self.parameters], "agrees": self.agrees}


def _resonance(f: FloatArray, fr: float, p: float) -> NDArray[np.complex128]:
    w, wr = 2 * np.pi * f, 2 * np.pi * fr
    return np.asarray(wr**2 / (wr**2 - w**2 + 2j * p * wr * w), dtype=np.complex128)


def monte_carlo(model_key: str, theta: FloatArray, frf: FrequencyResponse, free: NDArray[np.bool_],
                inputs: IdentInputs, *, names: tuple[str, ...], units: tuple[str, ...], u_linear: FloatArray,
                k: FloatArray, sources: tuple[str, ...], noise_scale: float = 1.0, noise_dof: float | None = None,
                trials: int = 1000, seed: int = 0) -> MonteCarloCheck:
    """The check (module docstring).  sources: those the linear budget propagates (nonzero); H is
    the response the estimate was fitted to (chain-corrected); u_linear, k per parameter (free ones)."""
    rng = np.random.default_rng(seed)
    theta = np.asarray(theta, float)
    free = np.asarray(free, bool)
    f, H = frf.f_hz, frf.H
    L = np.linalg.cholesky(frf.cov)
    ch = inputs.chain
    m_e, m_l = inputs.m_e, inputs.m_l
    draws = np.empty((trials, theta.size))
    for t in range(trials):
        Hd = H.copy()
        if "noise" in sources:
            scale = noise_scale * (rng.chisquare(noise_dof) / noise_dof if noise_dof else 1.0)
            z = np.einsum("nij,nj->ni", L, rng.standard_normal((f.size, 2))) * math.sqrt(scale)
            Hd = Hd + z[:, 0] + 1j * z[:, 1]
        if "chain_gain" in sources:
            Hd = Hd * (1 + ch.gain_rel_std * rng.standard_normal() + ch.flatness_rel_std * rng.standard_normal(f.size))
        if "chain_phase" in sources:
            ph = (np.deg2rad(ch.phase_offset_std_deg) * rng.standard_normal()
                  + np.deg2rad(ch.phase_std_deg) * rng.standard_normal(f.size))
            Hd = Hd * np.exp(1j * ph)
        if "chain_delay" in sources:
            Hd = Hd * np.exp(2j * np.pi * f * ch.delay_std_s * rng.standard_normal())
        if "chain_resonance" in sources and ch.displacement_resonance_hz is not None:
            fr, p = ch.displacement_resonance_hz, ch.displacement_damping
            fr2 = fr + ch.resonance_std_hz * rng.standard_normal()
            p2 = max(p + ch.displacement_damping_std * rng.standard_normal(), 0.0)
            Hd = Hd * _resonance(f, fr, p) / _resonance(f, fr2, p2)
        me = m_e + (inputs.end_mass.std or 0.0) * rng.standard_normal() if "end_mass" in sources else m_e
        ml = m_l + (inputs.load_mass.std or 0.0) * rng.standard_normal() if "load_mass" in sources else m_l
        trial = replace(frf, H=Hd)
        draws[t] = fit_frf(trial, make_model(model_key, me, ml), theta, free, inflate=False).theta
    params = []
    for i in np.nonzero(free)[0]:
        if not np.isfinite(u_linear[i]):
            continue
        x = draws[:, i]
        lo, hi = np.quantile(x, [0.025, 0.975])
        params.append(McParameter(names[i], units[i], float(theta[i]), float(u_linear[i]), float(k[i]),
                                  float(x.mean()), float(x.std(ddof=1)), float(lo), float(hi)))
    return MonteCarloCheck(trials, seed, tuple(sources), tuple(params))



def check_result(rec: Any, result: Any, *, frf: FrequencyResponse | None = None, trials: int = 1000, seed: int = 0,
                 p: float = 0.95) -> MonteCarloCheck:
    """The check of a stored frequency-domain ``IdentificationResult`` of recording ``rec``: the inputs
    from the recording as identify took them, H(f) the stored one (``frf``, before the chain's
    correction) or the recording's, the sources and k from the result's budget."""
    from station.errors import StationError
    from station.ident.coverage import coverages
    from station.ident.inputs import inputs_for
    from station.ident.response.checked import checked_response
    from station.ident.structure import chain_corrected

    if result.method != "fd" or not result.budget:
        raise StationError(f"the Monte Carlo check needs a frequency-domain result with a budget, "
                           f"not {result.method}")
    inputs = inputs_for(rec)
    frf = chain_corrected(frf if frf is not None else checked_response(rec, inputs).frf, inputs.chain)
    model = make_model(result.model, inputs.m_e, inputs.m_l)
    names, units = tuple(model.names), tuple(model.units)
    est = [result.parameters.get(n) for n in names]
    free = np.array([e is not None and e.identifiable and e.value is not None and n in result.budget
                     for n, e in zip(names, est, strict=True)])
    theta = np.array([e.value if e is not None and e.value is not None else 0.0 for e in est], float)
    cov = coverages(result.budget, p)
    u = np.array([cov[n].u if n in cov else np.nan for n in names])
    k = np.array([cov[n].k if n in cov else np.nan for n in names])
    contrib = [b.stds for b in result.budget.values()]
    sources = tuple(s for s in contrib[0] if any((c.get(s) or 0.0) > 0 for c in contrib))
    dof = next((b.dof["noise"] for b in result.budget.values() if b.dof.get("noise")), None)
    scale = float(result.fit.chi2_per_dof) if dof else 1.0
    return monte_carlo(result.model, theta, frf, free, inputs, names=names, units=units, u_linear=u, k=k,
                       sources=sources, noise_scale=scale, noise_dof=dof, trials=trials, seed=seed)
