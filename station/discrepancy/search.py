"""Fitting one candidate effect on top of the current model (the base model's start values:
``eiv.base_start``, re-exported here)."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from station.discrepancy.catalogue import LOWPASS_ORDERS, absent, start_grid
from station.discrepancy.data import RigData
from station.discrepancy.eiv import base_start
from station.discrepancy.fit import ModelFit, Problem, fit_model, fit_unless_above, profiled_chi2

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Candidate:
    """One catalogue effect tried in one round: chi^2 decrease (scaled by the Birge ratio of the
    larger model), added parameters, p-value of the likelihood-ratio test, Delta BIC (> 0 favours the
    effect), gap after (V)."""

    name: str
    delta_chi2: float
    added_params: int
    p_value: float
    delta_bic: float
    gap_V: float
__all__ = ["base_start", "fit_candidate"]
FUNDAMENTAL_ONLY = ("coupling_compliance", "conditioner_lowpass", "channel_delay", "displacement_resonance",
                    "clock_skew")
# LM runs from the best grid points
MULTI_START: dict[str, int] = {"coupling_compliance": 3, "displacement_resonance": 2}
# the smallest chi^2 decrease any use of a candidate's fit looks at (``ties.undetectable``: Delta chi^2 / B >= 1)
SMALLEST_DCHI2 = 1.0
# a fit from a grid point of an effect whose absence is a bound is given up if after this many model
# evaluations its chi^2 is not yet within ``SMALLEST_DCHI2`` of what the absence reached
GRID_PATIENCE_NFEV = 100


def fit_candidate(data: RigData, current: ModelFit, name: str) -> ModelFit | None:
    """Add effect ``name`` to the current model with its parameters free and fit, from the best
    points of its start grid (``_fits``: for an effect whose absence is a bound, from that absence
    first).  The low-pass order is enumerated; the best order by chi^2 is kept.  None if the effect
    cannot be fitted on this recording (e.g. mains lines without a mains line found)."""
    if name == "mains_interference" and data.n_mains == 0:
        return None
    if name == "coupling_compliance" and data.end_mass_kg <= 0:
        return None
    if name in FUNDAMENTAL_ONLY and data.n_steps < 3:
        # 2 numbers per step for S, k_f, b_f and the effect's own: no degree of freedom left to test it
        return None
    lp = "conditioner_lowpass"
    variants: list[dict[str, int]]
    if name == lp:
        variants = [{**current.effects, name: o} for o in LOWPASS_ORDERS]
    elif lp in current.effects:
        # the low-pass order was chosen without this effect: let it move by one (a low-pass of the
        # wrong order can absorb part of e.g. a coupling and hold the search in a local optimum)
        o = current.effects[lp]
        variants = [{**current.effects, lp: k, name: 0} for k in (o, o - 1, o + 1) if k in LOWPASS_ORDERS]
    else:
        variants = [{**current.effects, name: 0}]
    best: ModelFit | None = None
    alts: list[tuple[int, float, float, float]] = []
    grid = start_grid(name, data, current.values)
    for effects in variants:
        order = effects.get(lp, 0)
        fits = _fits(data, effects, current.values, grid, MULTI_START.get(name, 1), absent(name, data))
        if not fits:
            continue
        best_order = min(fits, key=lambda f: f.chi2)
        alts.append((order, best_order.chi2, best_order.values["k_f"], best_order.values["b_f"]))
        if best is None or best_order.chi2 < best.chi2:
            best = best_order
    if best is not None and lp in best.effects:
        best = replace(best, alternatives=tuple(alts))
    return best


def _fit(data: RigData, effects: Mapping[str, int], start: dict[str, float], below: float = math.inf
         ) -> list[ModelFit]:
    """``fit_model`` as a list of none or one fit (a fit that fails is logged, not raised).  With
    ``below`` (the chi^2 the effect's absence reached) a fit still above ``below`` + ``SMALLEST_DCHI2``
    after ``GRID_PATIENCE_NFEV`` evaluations is given up (``fit.fit_unless_above``): a start crawling
    back towards the absence through the model's flat directions, which it would not beat."""
    try:
        if math.isfinite(below):
            fit = fit_unless_above(data, effects, start, below + SMALLEST_DCHI2, GRID_PATIENCE_NFEV)
            if fit is None:
                log.debug("candidate %s from %s given up: not below %.6g after %d evaluations", effects, start,
                          below + SMALLEST_DCHI2, GRID_PATIENCE_NFEV)
            return [] if fit is None else [fit]
        return [fit_model(data, effects, start)]
    except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
        log.info("candidate %s failed: %s", effects, exc)
        return []


def _fits(data: RigData, effects: Mapping[str, int], values: Mapping[str, float], grid: list[dict[str, float]],
          n: int, none: dict[str, float] | None) -> list[ModelFit]:
    """The fits from the n grid points with the lowest profiled chi^2.  For an effect whose absence
    ``none`` is a bound (a rigid coupling, no low-pass) the fit from that absence comes first (a few
    steps when the effect is not in the data, where a fit from a grid point crawls through the model's
    flat directions back towards it for its whole budget, or stops in a local minimum above it); the
    grid is then fitted only if a grid point's profiled chi^2 promises at least ``SMALLEST_DCHI2``
    below what the absence reached."""
    if len(grid) == 1 and none is None:
        return _fit(data, effects, {**values, **grid[0]})
    out = [] if none is None else _fit(data, effects, {**values, **none})
    scores = []
    for g in grid:
        prob = Problem(data, effects, {**values, **g})
        try:
            scores.append(profiled_chi2(prob, np.zeros(len(prob.params))))
        except (ValueError, np.linalg.LinAlgError, FloatingPointError):
            scores.append(np.inf)
    reached = min((f.chi2 for f in out), default=math.inf)
    if out and not min(scores) < reached - SMALLEST_DCHI2:
        return out
    for i in np.argsort(scores)[:n]:
        out += _fit(data, effects, {**values, **grid[int(i)]}, reached)
    return out


def with_order_alternatives(data: RigData, final: ModelFit) -> ModelFit:
    """The final model with the k_f, b_f of every low-pass order refitted on top of all its other
    effects (``alternatives``; an effect named after the low-pass let its order move by one only, so
    orders that fit as well would be missing from the average); the best order's fit replaces the
    final one if it is better."""
    lp = "conditioner_lowpass"
    if lp not in final.effects:
        return final
    rest = {k: v for k, v in final.effects.items() if k != lp}
    try:
        reduced = fit_model(data, rest, final.values)
    except (ValueError, np.linalg.LinAlgError, FloatingPointError):
        return final
    again = fit_candidate(data, reduced, lp)
    if again is None:
        return final
    return again if again.chi2 < final.chi2 else replace(final, alternatives=again.alternatives)
