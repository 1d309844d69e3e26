"""The next run that settles it: steps within the rig's limits that separate tied explanations, or
determine a transducer parameter the plan leaves uncertain.

Ties.  Models A and B (the named effect and each runner-up that fits as well) differ in their
predictions at frequencies the plan did not visit.  For a planned set of steps the expected
Delta chi^2 of B when A is true is the chi^2 of B refitted (all its parameters free) to A's noise-free
predictions on the measured steps plus the planned ones, weighted with the measured noise
(``design.expected_chi2``; the non-centrality of the likelihood-ratio statistic).  The proposal
maximises the smallest such value over all ordered pairs of tied models: candidate steps are the rig's
frequency range on a log grid, each at the largest radius that keeps the peak force within
``FILL`` of the limit under every tied model (the dynamic amplification |G(w)| / (M w^2) of each model
included, paper Eq. 8/9) and passes ``station.limits.check_steps``; steps are added greedily on the
first-order refit (``design.projected_chi2``) until the smallest Delta chi^2 reaches ``TARGET_DCHI2``
or ``MAX_NEW_STEPS``; the reported gain is then the exact refit.  ``TARGET_DCHI2`` = 50: the
statistic then exceeds the tie margin (Delta BIC 10 plus the parameter-count term) with a wide margin
(its noise is about 2 sqrt(Delta chi^2) = 14).

A parameter.  Without a tie, when k_f is known to worse than ``KF_REL`` (relative standard
uncertainty, e.g. k_f against a free coupling stiffness), steps are chosen the same way to minimise
var(k_f) from the Fisher information J^T J of the final model (D_s-optimal for k_f); the gain is
0.5 log2(var before / var after) in bits.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, TypedDict

import numpy as np

from drivers.rig.model import spring_force_per_acceleration
from drivers.rig.params import CouplingCompliance, Transducer
from station.config import StationConfig, StepSpec
from station.discrepancy.data import FloatArray, G, RigData
from station.discrepancy.design import (
    expected_chi2,
    linearised,
    planned_data,
    projected_chi2,
    with_model,
)
from station.discrepancy.fit import ModelFit
from station.errors import LimitError
from station.limits import check_steps, force_limit_N

log = logging.getLogger(__name__)
TARGET_DCHI2 = 50.0
MAX_NEW_STEPS = 4
N_GRID = 24
FILL = 0.9
KF_REL = 0.01
KF_REL_TARGET = 0.002


@dataclass(frozen=True)
class RunContext:
    """What the proposal needs besides the data: the station configuration the run was made with
    (limits, plan times) and the run's nominal steps (Hz, m)."""

    config: StationConfig
    steps: tuple[tuple[float, float], ...]


class PairJson(TypedDict):
    """A pair of tied models: the one taken as true, the one refitted, Delta chi^2 now and after the steps
    (None if not finite)."""

    truth: str
    refitted: str
    delta_chi2_now: float | None
    delta_chi2_after: float | None


class ProposalJson(TypedDict):
    """``Proposal.to_json``: steps in Hz and m; the information gain as ``measure`` says (None if not finite)."""

    reason: str
    steps: list[dict[str, float]]  # crank_frequency_hz (Hz), crank_radius_m (m): a request's step
    run_steps: list[dict[str, float]]
    expected_information_gain: float | None
    measure: str
    current: float | None
    separates: list[str]
    record_s: float
    pairs: list[PairJson]


@dataclass(frozen=True)
class Proposal:
    """Steps to add (crank frequency Hz, radius m), the whole run to make (the run's own steps and
    the added ones), the expected information gain (``measure``: "delta_chi2", the smallest expected
    Delta chi^2 between the tied models, or "bits" for a parameter) before and after, the models or
    parameter it separates, and per pair (truth, refitted, Delta chi^2 now, after)."""

    reason: str
    steps: tuple[tuple[float, float], ...]
    run_steps: tuple[tuple[float, float], ...]
    expected_information_gain: float
    measure: str
    current: float
    separates: tuple[str, ...]
    record_s: float
    pairs: tuple[tuple[str, str, float, float], ...] = field(default_factory=tuple)

    def to_json(self) -> ProposalJson:
        def steps(s: Sequence[tuple[float, float]]) -> list[dict[str, float]]:
            return [{"crank_frequency_hz": f, "crank_radius_m": r} for f, r in s]
        return {"reason": self.reason, "steps": steps(self.steps), "run_steps": steps(self.run_steps),
                "expected_information_gain": _num(self.expected_information_gain), "measure": self.measure,
                "current": _num(self.current), "separates": list(self.separates), "record_s": self.record_s,
                "pairs": [{"truth": a, "refitted": b, "delta_chi2_now": _num(x), "delta_chi2_after": _num(y)}
                          for a, b, x, y in self.pairs]}


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _amplification(fit: ModelFit, data: RigData, f: np.ndarray) -> np.ndarray:
    """|F_1| / (M w^2 r) of the model (transducer, coupling if in it), per frequency."""
    v = fit.values
    t = Transducer(k_f=v["k_f"], b_f=v["b_f"], m_e=data.end_mass_kg, m_l=data.load_mass_kg,
                   sensitivity_V_per_N=v["S"], capacity_N=data.capacity_N)
    cpl = CouplingCompliance(v["k_c"], v["b_c"]) if "coupling_compliance" in fit.effects else None
    return np.abs(spring_force_per_acceleration(t, cpl, f)) / data.total_mass_kg


def candidate_steps(cfg: StationConfig, data: RigData, fits: Sequence[ModelFit]) -> list[tuple[float, float]]:
    """The rig's frequency range on a log grid, each at the largest radius (3 significant digits,
    rounded down) within ``FILL`` of the force limit under every model, inside the radius range, and
    within ``FILL`` of the displacement channel's range (sensor gain times radius: a clipped
    displacement is no measurement)."""
    fr, rr = cfg.rig.crank_frequency_hz, cfg.rig.crank_radius_m
    freqs = np.unique([float(f"{f:.3g}") for f in np.geomspace(max(fr.min, 0.5), fr.max, N_GRID)])
    freqs = freqs[(freqs >= fr.min) & (freqs <= fr.max)]
    amp = np.max([_amplification(fit, data, freqs) for fit in fits], axis=0)
    M = data.total_mass_kg
    # the displacement channel must not clip either: r gain within FILL of the ADC's range
    r_range = FILL * cfg.daq.displacement_range_V / cfg.displacement_sensor.gain_V_per_m
    out = []
    for f, a in zip(freqs, amp, strict=True):
        w2 = (2 * math.pi * f) ** 2
        r = FILL * (force_limit_N(cfg) / M - G) / (max(a, 1.0) * w2)
        r = min(r, rr.max, r_range)
        r = _floor3(r) if r > 0 else 0.0
        if r < rr.min:
            continue
        try:
            check_steps(cfg, [StepSpec.model_construct(crank_frequency_hz=float(f), crank_radius_m=float(r))])
        except LimitError:
            continue
        out.append((float(f), r))
    return out


def _floor3(x: float) -> float:
    """x rounded down to 3 significant digits."""
    e = math.floor(math.log10(x)) - 2
    return float(f"{math.floor(x / 10**e) * 10**e:.3g}")


def linear_variance(J: FloatArray, i: int, tol: float = 1e-6) -> float:
    """Variance of internal variable ``i`` from the Fisher information ``J^T J`` (J: rows x params,
    whitened); ``inf`` when the rows do not determine it (e_i outside the row space of J: the
    pseudo-inverse would report 0 there, i.e. a perfectly known parameter)."""
    M = J.T @ J
    P = np.linalg.pinv(M)
    e = np.zeros(M.shape[0])
    e[i] = 1.0
    if not np.linalg.norm(M @ P[:, i] - e) < tol:
        return math.inf
    return float(P[i, i])


def _greedy(score: Any, n_cand: int, stop: Any) -> list[int]:
    chosen: list[int] = []
    for _ in range(MAX_NEW_STEPS):
        best, best_s = -1, -math.inf
        for j in range(n_cand):
            if j in chosen:
                continue
            s = score([*chosen, j])
            if s > best_s:
                best, best_s = j, s
        if best < 0:
            break
        chosen.append(best)
        if stop(best_s):
            break
    return chosen


def propose_tie(data: RigData, models: Sequence[tuple[str, ModelFit]], ctx: RunContext) -> Proposal | None:
    """Steps that separate every pair of the tied ``models`` (label, fit); None when no step fits
    within the limits."""
    cfg = ctx.config
    cands = candidate_steps(cfg, data, [m for _, m in models])
    if not cands:
        return None
    rec, gap = cfg.plan.record_s, cfg.plan.settle_s + cfg.plan.record_s
    full = planned_data(data, cands, rec, gap)
    n0 = data.n_steps
    pairs = [(a, b) for a in range(len(models)) for b in range(len(models)) if a != b]
    lin = {}
    for a, b in pairs:
        r, J, rows, _ = linearised(with_model(full, models[a][1]), models[b][1])
        lin[(a, b)] = (r, J, rows)

    def score(sel: list[int]) -> float:
        want = np.r_[np.arange(n0), n0 + np.array(sel, dtype=int)]
        return min(projected_chi2(r, J, np.isin(rows, want)) for r, J, rows in lin.values())

    chosen = sorted(_greedy(score, len(cands), lambda s: s >= TARGET_DCHI2), key=lambda j: cands[j][0])
    new = [cands[j] for j in chosen]
    now_design = planned_data(data, [], rec, gap)
    new_design = planned_data(data, new, rec, gap)
    rows_out = []
    for a, b in pairs:
        now = expected_chi2(with_model(now_design, models[a][1]), models[b][1])
        after = expected_chi2(with_model(new_design, models[a][1]), models[b][1])
        rows_out.append((models[a][0], models[b][0], now, after))
    after_min = min(r[3] for r in rows_out)
    now_min = min(r[2] for r in rows_out)
    names = tuple(m[0] for m in models)
    return Proposal(
        reason=(f"{' / '.join(names)} fit the data equally well (smallest expected Delta chi2 between them "
                f"{now_min:.3g}); {len(new)} added step(s) raise it to {after_min:.3g}"),
        steps=tuple(new), run_steps=_run_steps(ctx, new), expected_information_gain=after_min,
        measure="delta_chi2", current=now_min, separates=names, record_s=rec, pairs=tuple(rows_out))


def propose_parameter(data: RigData, final: ModelFit, ctx: RunContext, name: str = "k_f") -> Proposal | None:
    """Steps that minimise var(``name``) of the final model (module docstring); None if not needed."""
    rel = final.std[name] / abs(final.values[name])
    if not rel > KF_REL:
        return None
    cfg = ctx.config
    cands = candidate_steps(cfg, data, [final])
    if not cands:
        return None
    rec, gap = cfg.plan.record_s, cfg.plan.settle_s + cfg.plan.record_s
    _, J, rows, prob = linearised(with_model(planned_data(data, cands, rec, gap), final), final)
    i = [q.name for q in prob.params].index(name)
    n0 = data.n_steps

    def var(sel: list[int]) -> float:
        keep = np.isin(rows, np.r_[np.arange(n0), n0 + np.array(sel, dtype=int)])
        return linear_variance(J[keep], i)

    v0 = var([])
    if not 0.0 < v0 < math.inf:
        # The measured steps leave the parameter free to first order (e.g. one step): no ratio of
        # variances to aim at or report; the parameter's own statement says it is not identifiable.
        log.info("no step proposal for %s: the measured steps do not determine it to first order", name)
        return None
    target = v0 * (KF_REL_TARGET / rel) ** 2
    chosen = sorted(_greedy(lambda s: -var(s), len(cands), lambda s: -s <= target), key=lambda j: cands[j][0])
    new = [cands[j] for j in chosen]
    v1 = var(chosen)
    bits = 0.5 * math.log2(v0 / v1) if v1 > 0 else math.inf
    rel1 = rel * math.sqrt(v1 / v0)
    return Proposal(
        reason=(f"{name} is determined to {100 * rel:.2g} % only (model {', '.join(final.effects) or 'base'}); "
                f"{len(new)} added step(s) would bring it to about {100 * rel1:.2g} %"),
        steps=tuple(new), run_steps=_run_steps(ctx, new), expected_information_gain=bits, measure="bits",
        current=0.0, separates=(name,), record_s=rec)


def _run_steps(ctx: RunContext, new: Sequence[tuple[float, float]]) -> tuple[tuple[float, float], ...]:
    """The run's own steps followed by the new ones (one recording holds everything the analysis needs)."""
    return tuple(ctx.steps) + tuple(new)


def next_run(data: RigData, final: ModelFit, added: Sequence[Any], ctx: RunContext | None, *,
             alpha: float, margin: float, coupled: ModelFit | None = None) -> Proposal | None:
    """The proposal for a finished analysis: for the first named effect whose round had runners-up
    within ``margin`` of Delta BIC (and p < ``alpha``), the final model with the named effect replaced
    by each of them is fitted and the tie proposed away; without a tie, k_f if it is poorly determined.
    ``coupled``: the final model with a coupling free, when it leaves k_f of the transducer alone
    undetermined (``structure``): the steps that determine k_f under it come first (settling a tie
    between models that all rest on a stiff coupling would not tell k_f).
    None without a run context (no limits known) or when nothing needs settling."""
    if ctx is None:
        return None
    if coupled is not None:
        prop = propose_parameter(data, coupled, ctx)
        if prop is not None:
            return replace(prop, reason="k_f of the transducer alone is not determined with a coupling free "
                                        f"(the data give the series stiffness): {prop.reason}")
    from station.discrepancy.fit import fit_model
    from station.discrepancy.search import fit_candidate

    for e in added:
        named = next((c for c in e.candidates if c.name == e.name), None)
        if named is None:
            continue
        tied = [c.name for c in e.candidates if c.name != e.name and c.name not in final.effects
                and c.p_value < alpha and named.delta_bic - c.delta_bic < margin]
        tied += [t for t in getattr(e, "tied", ()) if t != e.name and t not in tied and t not in final.effects]
        if not tied:
            continue
        rest = {k: v for k, v in final.effects.items() if k != e.name}
        try:
            reduced = fit_model(data, rest, final.values)
        except (ValueError, np.linalg.LinAlgError, FloatingPointError):
            continue
        models: list[tuple[str, ModelFit]] = [(e.name, final)]
        for name in tied:
            alt = fit_candidate(data, reduced, name)
            if alt is not None:
                models.append((name, alt))
        if len(models) >= 2:
            return propose_tie(data, models, ctx)
    return propose_parameter(data, final, ctx)
