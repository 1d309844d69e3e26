"""Control charts of a check standard's (or a transducer's) values over time.

Shewhart chart of individual values (NIST/SEMATECH e-Handbook 2.2.3.1, check standards): centre line
the mean of the reference values, limits mean ± k·s with k the two-sided t-quantile of the stated
probability (default 0.9973, the normal 3σ) on n - 1 degrees of freedom, s the reference values'
standard deviation (or, when larger, their mean stated uncertainty: a scatter below the values' own
uncertainty would make limits tighter than the measurement can hold).

EWMA chart (e-Handbook 6.3.2.4): z_0 = target, z_t = λ·x_t + (1 - λ)·z_{t-1}; limits
target ± L·s·sqrt(λ / (2 - λ)) (the asymptotic limits the e-Handbook draws; ``exact=True`` gives the
time-varying ones, λ/(2-λ)·[1 - (1-λ)^(2t)]).  Defaults λ = 0.2 and L = 3 (the e-Handbook's range
0.2-0.3 and its L).

Run lengths: ``shewhart_arl`` exactly, ``ewma_arl`` by the Markov-chain approximation of Brook and
Evans (1972) with the in-control band cut into ``states`` cells: the expected number of points until
an alarm for a mean shifted by δ (in units of s).  The false-alarm rate is 1/ARL(0).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from station.trend.tails import norm_cdf, norm_sf, t_ppf

Values = Sequence[float] | np.ndarray

SHEWHART_PROBABILITY = 0.9973  # two-sided coverage of the normal ±3σ
EWMA_LAMBDA = 0.2
EWMA_L = 3.0


@dataclass(frozen=True)
class ChartPoint:
    """One charted point: the value (or EWMA statistic) and whether it lies outside the limits."""

    index: int
    value: float
    statistic: float
    lower: float
    upper: float
    out_of_control: bool


@dataclass(frozen=True)
class Chart:
    """A control chart: kind ("shewhart" or "ewma"), centre line, its parameters, the points.

    ``reference`` is how many leading values set the centre and s (phase I); the later points are
    judged against them (phase II).  ``false_alarm_rate`` is the in-control probability of an alarm
    per point (1/ARL(0)); ``out_of_control`` lists the indices of the points outside the limits."""

    kind: str
    centre: float
    s: float
    reference: int
    parameters: dict[str, float]
    points: tuple[ChartPoint, ...]
    false_alarm_rate: float

    @property
    def out_of_control(self) -> list[int]:
        return [p.index for p in self.points if p.out_of_control]

    def to_dict(self) -> dict[str, object]:
        return {"kind": self.kind, "centre": self.centre, "s": self.s, "reference": self.reference,
                "parameters": dict(self.parameters), "false_alarm_rate": self.false_alarm_rate,
                "out_of_control": self.out_of_control,
                "points": [p.__dict__ | {} for p in self.points]}


def _finite(values: Values) -> np.ndarray:
    x = np.asarray(values, dtype=float)
    if x.ndim != 1 or x.size == 0:
        raise ValueError("a control chart needs a non-empty series of values")
    if not np.all(np.isfinite(x)):
        raise ValueError("a control chart's values must be finite")
    return x


def reference_statistics(values: Values, uncertainties: Values | None = None,
                         reference: int | None = None) -> tuple[float, float, int]:
    """Centre, s and the number of reference values: the first ``reference`` values (all by default).
    s is the larger of their standard deviation and their root-mean-square stated uncertainty."""
    x = _finite(values)
    n = x.size if reference is None else int(reference)
    if not 2 <= n <= x.size:
        raise ValueError(f"the reference needs at least 2 of the {x.size} values (asked for {n})")
    ref = x[:n]
    s = float(np.std(ref, ddof=1))
    if uncertainties is not None:
        u = np.asarray(uncertainties, dtype=float)[:n]
        u = u[np.isfinite(u)]
        if u.size:
            s = max(s, float(np.sqrt(np.mean(u**2))))
    return float(np.mean(ref)), s, n


def shewhart(values: Values, *, uncertainties: Values | None = None,
             reference: int | None = None, probability: float = SHEWHART_PROBABILITY) -> Chart:
    """Shewhart chart of individual values with t-limits (see the module)."""
    x = _finite(values)
    centre, s, n = reference_statistics(x, uncertainties, reference)
    k = float(t_ppf(0.5 + probability / 2, n - 1))
    lo, hi = centre - k * s, centre + k * s
    points = tuple(ChartPoint(i, float(v), float(v), lo, hi, bool(v < lo or v > hi)) for i, v in enumerate(x))
    return Chart("shewhart", centre, s, n, {"k": k, "probability": probability, "dof": n - 1}, points,
                 1.0 - probability)


def ewma(values: Values, *, target: float | None = None, s: float | None = None,
         uncertainties: Values | None = None, reference: int | None = None,
         lam: float = EWMA_LAMBDA, L: float = EWMA_L, exact: bool = False) -> Chart:
    """EWMA chart (see the module).  target and s default to the reference values' mean and s."""
    if not 0 < lam <= 1:
        raise ValueError(f"the EWMA weight λ must be in (0, 1], not {lam}")
    if not L > 0:
        raise ValueError(f"the EWMA limit factor L must be > 0, not {L}")
    x = _finite(values)
    if target is None or s is None:
        c, sd, n = reference_statistics(x, uncertainties, reference)
        target = c if target is None else target
        s = sd if s is None else s
    else:
        n = 0
    z = float(target)
    points = []
    for i, v in enumerate(x):
        z = lam * float(v) + (1 - lam) * z
        factor = lam / (2 - lam) * ((1 - (1 - lam) ** (2 * (i + 1))) if exact else 1.0)
        half = L * s * math.sqrt(factor)
        points.append(ChartPoint(i, float(v), z, target - half, target + half,
                                 bool(abs(z - target) > half)))
    arl0 = ewma_arl(0.0, lam=lam, L=L)
    return Chart("ewma", float(target), float(s), n, {"lambda": lam, "L": L}, tuple(points), 1.0 / arl0)


def shewhart_arl(shift: float, *, k: float = 3.0) -> float:
    """Average run length of a Shewhart chart with limits ±k (in s) for a mean shifted by ``shift`` s."""
    p = norm_sf(k - shift) + norm_cdf(-k - shift)
    return float(1.0 / p)


def _ewma_chain(lam: float, L: float, states: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Cells of the in-control band of an EWMA (in units of s): edges, midpoints, the start cell."""
    h = L * math.sqrt(lam / (2 - lam))
    edges = np.linspace(-h, h, states + 1)
    mids = 0.5 * (edges[:-1] + edges[1:])
    start = min(max(int(np.searchsorted(edges, 0.0) - 1), 0), states - 1)
    return edges, mids, start


def _ewma_transitions(edges: np.ndarray, mids: np.ndarray, lam: float, shift: float) -> np.ndarray:
    """P[i, j]: from cell i (z = mids[i]) to cell j, λx + (1-λ)z in cell j, x ~ N(shift, 1)."""
    lo = (edges[None, :-1] - (1 - lam) * mids[:, None]) / lam
    hi = (edges[None, 1:] - (1 - lam) * mids[:, None]) / lam
    return np.asarray(norm_cdf(hi - shift) - norm_cdf(lo - shift))


@lru_cache(maxsize=64)
def ewma_arl(shift: float, *, lam: float = EWMA_LAMBDA, L: float = EWMA_L, states: int = 201) -> float:
    """Average run length of an EWMA chart (asymptotic limits ±L·sqrt(λ/(2-λ)) in units of s) for a
    mean shifted by ``shift`` s, by the Brook-Evans Markov chain with ``states`` in-control cells."""
    edges, mids, start = _ewma_chain(lam, L, states)
    P = _ewma_transitions(edges, mids, lam, shift)
    arl = np.linalg.solve(np.eye(states) - P, np.ones(states))
    return float(arl[start])


def first_alarm_probabilities(shifts: Sequence[float], *, kind: str = "ewma", lam: float = EWMA_LAMBDA,
                              L: float = EWMA_L, states: int = 201) -> np.ndarray:
    """The probability that the first alarm comes at point i (i = 0..n-1) when point i's mean is
    shifted by ``shifts[i]`` (in units of s): a step is a constant shift from some point on, a drift a
    growing one.  ``kind`` "shewhart" uses limits ±L.  What the probabilities leave to 1 is the chance
    of no alarm within the n points."""
    d = np.asarray(shifts, dtype=float)
    if kind == "shewhart":
        p = norm_sf(L - d) + norm_cdf(-L - d)
        survive = np.concatenate([[1.0], np.cumprod(1 - p)[:-1]])
        return np.asarray(p * survive)
    if kind != "ewma":
        raise ValueError(f"unknown chart kind {kind!r}")
    edges, mids, start = _ewma_chain(lam, L, states)
    mass = np.zeros(states)
    mass[start] = 1.0
    out = np.empty(d.size)
    cache: dict[float, np.ndarray] = {}
    for i, shift in enumerate(d):
        P = cache.get(float(shift))
        if P is None:
            P = cache[float(shift)] = _ewma_transitions(edges, mids, lam, float(shift))
        nxt = mass @ P
        out[i] = mass.sum() - nxt.sum()
        mass = nxt
    return out
