"""Fitting one candidate effect on top of the current model (the base model's start values:
``eiv.base_start``, re-exported here)."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from station.discrepancy.catalogue import LOWPASS_ORDERS, start_grid
from station.discrepancy.data import RigData
from station.discrepancy.eiv import base_start
from station.discrepancy.fit import ModelFit, Problem, fit_model, profiled_chi2

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


def fit_candidate(data: RigData, current: ModelFit, name: str) -> ModelFit | None:
    """Add effect ``name`` to the current model with its parameters free, start from the best point
    of its start grid (profiled chi^2, all other parameters free to first order), and fit.  The
    low-pass order is enumerated; the best order by chi^2 is kept.  None if the effect cannot be
    fitted on this recording (e.g. mains lines without a mains line found)."""
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
    n_starts = MULTI_START.get(name, 1)
    for effects in variants:
        order = effects.get(lp, 0)
        grid = start_grid(name, data, current.values)
        best_order: ModelFit | None = None
        for start in _best_starts(data, effects, current.values, grid, n_starts):
            try:
                fit = fit_model(data, effects, start)
            except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
                log.info("candidate %s (order %d) failed: %s", name, order, exc)
                continue
            if best_order is None or fit.chi2 < best_order.chi2:
                best_order = fit
        if best_order is None:
            continue
        alts.append((order, best_order.chi2, best_order.values["k_f"], best_order.values["b_f"]))
        if best is None or best_order.chi2 < best.chi2:
            best = best_order
    if best is not None and lp in best.effects:
        best = replace(best, alternatives=tuple(alts))
    return best


def _best_starts(data: RigData, effects: Mapping[str, int], values: Mapping[str, float],
                 grid: list[dict[str, float]], n: int) -> list[dict[str, float]]:
    """The n grid points with the lowest profiled chi^2, as full start dictionaries."""
    if len(grid) == 1:
        return [{**values, **grid[0]}]
    scores = []
    for g in grid:
        start = {**values, **g}
        prob = Problem(data, effects, start)
        try:
            scores.append(profiled_chi2(prob, np.zeros(len(prob.params))))
        except (ValueError, np.linalg.LinAlgError, FloatingPointError):
            scores.append(np.inf)
    return [{**values, **grid[int(i)]} for i in np.argsort(scores)[:n]]


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
