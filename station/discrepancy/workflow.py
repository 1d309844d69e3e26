"""The model-gap workflow: fit the base model, find where it disagrees, name the missing effects one
at a time, show the gap shrink, say what is left.

Selection rule (forward, greedy): every catalogue effect not yet in the model is added with its
parameters free and the whole model refitted.  Its evidence is the likelihood-ratio statistic against
the measured noise, Delta chi^2 / B with B = max(1, chi^2/dof) of the best-fitting candidate of the
round, common to all candidates (the extra-sum-of-squares test: structure the catalogue cannot explain
inflates B rather than being forced onto a name),
referred to chi^2 with as many degrees of freedom as parameters were added.  Candidates are ranked by
Delta BIC = Delta chi^2 / B - k ln(n_obs) (in a tie, within ``AMBIGUOUS_BIC``, a candidate that fits only
with a parameter pinned at its physical bound yields to one that does not); the best is named only if
p < ``ALPHA``, Delta BIC > 0 and
it explains at least ``MIN_SHARE`` of the excess chi^2 - dof left by the current model (an effect that
only nibbles at a much larger misfit is not named: that misfit is reported by where it is instead).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.special import chdtrc

from station.discrepancy.catalogue import CATALOGUE
from station.discrepancy.data import RigData, prepare
from station.discrepancy.drive import check_drive
from station.discrepancy.eiv import noise_floor
from station.discrepancy.estimates import effect_estimates, transducer_parameters
from station.discrepancy.fit import ModelFit, fit_model
from station.discrepancy.locate import fundamental_table, in_basis, out_of_basis
from station.discrepancy.physical import implausible
from station.discrepancy.plausible import withdraw
from station.discrepancy.propose import FILL, KF_REL, RunContext, next_run
from station.discrepancy.result import AddedEffect, DiscrepancyResult
from station.discrepancy.search import Candidate, base_start, fit_candidate, with_order_alternatives
from station.discrepancy.structure import COUPLING as COUPLING_EFFECT
from station.discrepancy.structure import state_structure
from station.discrepancy.ties import TIE_CHI2, averaged, tie_models, tied_names, undetectable
from station.errors import StationError
from station.ident.result import Estimate
from station.ident.structure import state_stiff
from station.ident.uncertainty import UncertaintyBudget
from station.recording import Recording, read_recording

if TYPE_CHECKING:
    from station.config import StationConfig

log = logging.getLogger(__name__)
ALPHA = 1e-6
AMBIGUOUS_BIC = 10.0
MIN_SHARE = 0.25


def _candidate(current: ModelFit, fit: ModelFit, name: str, birge: float) -> Candidate:
    k = fit.n_par - current.n_par
    d = max(current.chi2 - fit.chi2, 0.0) / birge
    return Candidate(name=name, delta_chi2=d, added_params=k, p_value=float(chdtrc(k, d)) if k > 0 else math.nan,
                     delta_bic=d - k * math.log(fit.n_obs), gap_V=fit.gap_V)


def _evidence(best: Candidate, ranked: list[Candidate], before_gap: float, share: float,
              fits: dict[str, ModelFit]) -> str:
    text = (f"Delta chi2 = {best.delta_chi2:.4g} for {best.added_params} parameter(s) "
            f"({100 * min(share, 1.0):.3g} % of the excess), "
            f"p = {best.p_value:.2g}, Delta BIC = {best.delta_bic:.4g}; gap {before_gap:.4g} V -> "
            f"{best.gap_V:.4g} V")
    others = [c for c in ranked if c.name != best.name]
    if others:
        r = others[0]
        text += f"; runner-up {r.name} (Delta BIC {r.delta_bic:.4g})"
        if best.delta_bic - r.delta_bic < AMBIGUOUS_BIC and r.p_value < ALPHA:
            a, b = fits[best.name].values, fits[r.name].values
            text += (f" is nearly as good: the data barely distinguish the two (k_f {a['k_f']:.6g} vs "
                     f"{b['k_f']:.6g} N/m, b_f {a['b_f']:.5g} vs {b['b_f']:.5g} N*s/m)")
    return text


Round = tuple[ModelFit, list[AddedEffect], tuple[Candidate, ...], list[tuple[Candidate, ModelFit]]]


def _forward(data: RigData, current: ModelFit, allowed: tuple[str, ...], max_effects: int) -> Round:
    """Greedy forward selection from ``current`` over the ``allowed`` effects (module docstring).
    Returns the final fit, the named effects, the last round's candidates that were not named, and
    those candidates with their fits (for the effects the data cannot rule out)."""
    added: list[AddedEffect] = []
    rejected: tuple[Candidate, ...] = ()
    last: list[tuple[Candidate, ModelFit]] = []
    for _ in range(max_effects):
        fits: dict[str, ModelFit] = {}
        cands: list[Candidate] = []
        for name in allowed:
            if name in current.effects or (name == "clock_skew" and not data.common_clock):
                continue  # a clock skew needs the steps on one time axis
            fit = fit_candidate(data, current, name)
            if fit is None:
                continue
            fits[name] = fit
        # one Birge ratio for the whole round (that of the best-fitting candidate), so that the
        # candidates are ranked on the same scale
        birge = min((f.birge for f in fits.values()), default=1.0)
        cands = [_candidate(current, f, n, birge) for n, f in fits.items()]
        ranked = sorted(cands, key=lambda c: -c.delta_bic)
        for c in ranked:
            log.info("candidate %-24s dchi2/B %.4g k %d p %.3g dBIC %.4g gap %.4g V", c.name, c.delta_chi2,
                     c.added_params, c.p_value, c.delta_bic, c.gap_V)
        excess = max(current.chi2 - current.dof, 1e-300)
        ok = [c for c in ranked if c.p_value < ALPHA and c.delta_bic > 0
              and (current.chi2 - fits[c.name].chi2) >= MIN_SHARE * excess]
        if not ok:
            rejected = tuple(ranked)
            last = [(c, fits[c.name]) for c in ranked]
            break
        tied = tied_names(ok, fits, birge)
        best, tie = _choose(ok, tied, fits, current, data)
        if best is not ok[0]:
            ranked = [best] + [c for c in ranked if c.name != best.name]
        fit = fits[best.name]
        share = (current.chi2 - fit.chi2) / excess
        if len(tied) > 1:
            tie += (f"; TIE: {', '.join(t for t in tied if t != best.name)} fit(s) as well (chi2 within "
                    f"{TIE_CHI2:g}): the name is not decided by these data, see ties")
        added.append(AddedEffect(name=best.name, params=effect_estimates(fit, best.name), gap_after=fit.gap_V,
                                 gap_steps_after=tuple(float(g) for g in fit.gap_steps_V),
                                 evidence=_evidence(best, ranked, current.gap_V, share, fits) + tie,
                                 candidates=tuple(ranked), parameters=transducer_parameters(fit),
                                 tied=tied if len(tied) > 1 else ()))
        current = fit
    return current, added, rejected, last


def _choose(ok: list[Candidate], tied: tuple[str, ...], fits: dict[str, ModelFit], current: ModelFit,
            data: RigData) -> tuple[Candidate, str]:
    """The name to give among the significant candidates ``ok`` (ranked by Delta BIC) and the reason
    when it is not the first.  Inside a tie (chi^2 within ``TIE_CHI2``) Delta BIC only counts
    parameters (k ln n), which is no evidence: a candidate whose fit is physically impossible
    (``plausible.implausible``) or holds a parameter at its physical bound yields to one that is
    neither, and among those the lowest AIC (chi^2 / B + 2 k: a better fit by more than what its extra
    parameters buy by chance) is named."""
    best = ok[0]
    if best.name not in tied or len(tied) < 2:
        return best, ""
    group = [c for c in ok if c.name in tied]

    def rank(c: Candidate) -> tuple[bool, bool, float]:
        f = fits[c.name]
        return bool(implausible(c.name, f, data)), bool(_at_bound(f, current)), -c.delta_chi2 + 2 * c.added_params

    chosen = min(group, key=rank)
    if chosen is best:
        return best, ""
    why = implausible(best.name, fits[best.name], data)
    pinned = _at_bound(fits[best.name], current)
    if why:
        text = f"; named over {best.name}, whose fit is not physical ({why})"
    elif pinned:
        text = f"; named over {best.name}, which fits as well only with {pinned} (at its physical bound)"
    else:
        text = (f"; named over {best.name} (Delta BIC counts parameters only; {chosen.name} fits better by "
                f"Delta chi2/B {chosen.delta_chi2 - best.delta_chi2:.3g}, more than its extra parameters buy)")
    log.info("tie: %s", text[2:])
    return chosen, text


def _at_bound(fit: ModelFit, current: ModelFit) -> str:
    """A parameter the candidate added that the fit holds at a physical bound (e.g. b_c = 0), or ''.
    In a tie, a model that fits only with a parameter pinned at its bound is the weaker explanation."""
    old = {q.name for q in current.params}
    for q in (q for q in fit.params if q.name not in old):
        v, sd = fit.values[q.name], fit.std.get(q.name, 0.0)
        for b in (q.lower, q.upper):
            if math.isfinite(b) and abs(v - b) <= max(1e-3 * sd, 1e-12 * max(abs(b), 1.0)):
                return f"{q.name} = {b:g}"
    return ""


def _bic(fit: ModelFit, birge: float) -> float:
    return fit.chi2 / birge + fit.n_par * math.log(fit.n_obs)


def _swap(data: RigData, current: ModelFit) -> tuple[str, ...] | None:
    """Greedy selection can name an effect that, together with a later one, mimics a different
    pair (e.g. low-pass + delay for coupling + delay).  Try replacing each named effect by each
    other catalogue effect; return the better set if one is clearly better (BIC by more than
    ``AMBIGUOUS_BIC`` at the larger Birge ratio), else None."""
    best_set, best_bic = None, math.inf
    for named in current.effects:
        rest = {k: v for k, v in current.effects.items() if k != named}
        try:
            reduced = fit_model(data, rest, current.values)
        except (ValueError, np.linalg.LinAlgError):
            continue
        for other in CATALOGUE:
            if other in current.effects:
                continue
            fit = fit_candidate(data, reduced, other)
            if fit is None:
                continue
            b = max(fit.birge, current.birge)
            gain = _bic(current, b) - _bic(fit, b)
            if gain > AMBIGUOUS_BIC and _bic(fit, b) < best_bic:
                best_set, best_bic = (*rest, other), _bic(fit, b)
    return best_set


def analyse(data: RigData, max_effects: int = 4, recording: str = "",
            rec_notes: tuple[str, ...] = (), context: RunContext | None = None) -> DiscrepancyResult:
    """Run the workflow on decomposed data (see module docstring); with the run's ``context``
    (configuration and steps) the report carries the next run that would settle a tie."""
    t0 = time.perf_counter()
    base = fit_model(data, {}, base_start(data))
    current, added, rejected, last = _forward(data, base, CATALOGUE, max_effects)
    swapped = _swap(data, current) if len(added) >= 2 else None
    swap_note = ""
    if swapped is not None:
        swap_note = (f"greedy order named {', '.join(current.effects)}; the set {', '.join(swapped)} "
                     f"fits clearly better and replaces it")
        log.info(swap_note)
        current, added, _, _ = _forward(data, base, tuple(swapped), len(swapped))
        more, extra, rejected, last = _forward(data, current, CATALOGUE, max_effects - len(added))
        current, added = more, added + extra
    current = with_order_alternatives(data, current)
    # report every named effect's parameters from the final model (all effects present, so no
    # missing effect inflates or biases them); gaps stay those after each stage
    added = [AddedEffect(name=e.name, params=effect_estimates(current, e.name), gap_after=e.gap_after,
                         gap_steps_after=e.gap_steps_after, evidence=e.evidence, candidates=e.candidates,
                         parameters=e.parameters, tied=e.tied) for e in added]
    findings = in_basis(data, current)
    withdrawn, ties = withdraw(data, current, [e.name for e in added], findings)
    added = [e for e in added if e.name not in withdrawn]
    ties += [t for e in added if e.tied for t in [tie_models(data, current, e.name, e.tied)] if t is not None]
    ties += undetectable(data, current, last)
    after = transducer_parameters(current)
    after.update(averaged(current, ties, "; ".join(filter(None, (implausible(n, current, data)
                                                                 for n in current.effects)))))
    before = transducer_parameters(base)
    if data.n_steps < 2:
        why = ("one step: its force fundamental gives 2 numbers for S, k_f and b_f (and a coupling); they are "
               "not determined without assuming one of them")
        after = {k: Estimate(math.nan, math.nan, e.unit, False, why) for k, e in after.items()}
        before = {k: Estimate(math.nan, math.nan, e.unit, False, why) for k, e in before.items()}
    structure = state_structure(data, current, last) if data.n_steps >= 3 and data.end_mass_kg > 0 else None
    drive = check_drive(data)
    left = [*withdrawn.values(), *[f.text for f in findings], *drive.findings,
            *[f.text for f in out_of_basis(data)]]
    floor = noise_floor(data)
    if current.gap_V > 1.5 * floor and not left:
        left.append(f"gap {current.gap_V:.3g} V is {current.gap_V / floor:.3g} x the noise floor "
                    f"{floor:.3g} V but is not localised")
    notes = [*current.notes, drive.message]
    if swap_note:
        notes.append(swap_note)
    if rec_notes:
        notes += rec_notes
    notes += [f"step {i}: {why}" for i, why in data.excluded if "clipped" not in why]
    if data.n_steps < 4:
        notes.append(f"only {data.n_steps} steps: the fundamental gives {2 * data.n_steps} numbers for S, k_f, "
                     "b_f and the offset-free phase; coupling, low-pass and delay act on the fundamental only "
                     "and are hardly separable from the transducer parameters (more frequencies needed)")
    notes += [f"{t.kind}: {t.message}" for t in ties]
    if structure is not None:
        notes.append(f"structure: {structure.message}")
    if data.end_mass_kg <= 0:
        notes.append("no end mass in the recording: m_e = 0 assumed, coupling not testable")
    # k_f alone undetermined with a coupling on top, and no coupling among the ties (whose proposal
    # would separate it): propose for k_f under the coupling model first
    coupling_tied = any("coupling_compliance" in e.tied for e in added)
    proposal = next_run(data, current, added, context, alpha=ALPHA, margin=AMBIGUOUS_BIC,
                        coupled=None if structure is None or structure.k_f_alone_range is not None or coupling_tied
                        else structure.coupled)
    return DiscrepancyResult(
        recording=recording, base_gap=base.gap_V, final_gap=current.gap_V, noise_floor_V=floor,
        effects=tuple(added), parameters_before=before,
        parameters_after=after, unexplained=tuple(left), ties=tuple(ties), drive=drive,
        base_findings=tuple(f.text for f in in_basis(data, base)),
        steps=tuple(s.index for s in data.steps), f_hz=tuple(float(f) for f in data.f_hz),
        base_gap_steps=tuple(float(g) for g in base.gap_steps_V),
        final_gap_steps=tuple(float(g) for g in current.gap_steps_V), rejected=rejected,
        base_fundamental=fundamental_table(data, base), final_fundamental=fundamental_table(data, current),
        mains_search=data.mains.evidence, notes=tuple(notes), wall_s=time.perf_counter() - t0,
        proposal=proposal, proposal_note=_proposal_note(proposal, context, data), structure=structure)


def _proposal_note(proposal: Any, context: RunContext | None, data: RigData) -> str:
    """Why there is no proposal ('' when there is one)."""
    if proposal is not None:
        return ""
    if context is None:
        return "no follow-up run proposed: no rig limits known for this recording"
    if data.n_steps < 2:
        return "no follow-up run proposed: one step gives nothing to compare a plan against"
    return (f"nothing to propose: no tie left to settle and k_f is determined to better than {100 * KF_REL:g} % "
            "(or no step within the rig's limits would improve it)")


def analyse_recording(path: str | Path | Recording, max_effects: int = 4,
                      station: StationConfig | None = None) -> DiscrepancyResult:
    """The whole workflow on a recording (own or imported): ``station discrepancy`` and the daemon's
    ``GET /runs/{id}/discrepancy`` call this.  ``station``: the rig's configuration, whose limits a
    proposed follow-up run respects (default: those the recording states, ``run_context``)."""
    t0 = time.perf_counter()
    rec = path if isinstance(path, Recording) else read_recording(path)
    data = prepare(rec)
    events = tuple(str(d.get("warning")) for d in rec.documents if d.get("kind") == "event" and d.get("warning"))
    ctx = run_context(rec, station)
    rep = analyse(data, max_effects=max_effects, recording=str(rec.path), rec_notes=events,
                  context=ctx if isinstance(ctx, RunContext) else None)
    if isinstance(ctx, str):
        rep = replace(rep, proposal_note=ctx)
    ident = _identify(rec) if data.n_steps >= 2 else None
    before, after, notes = rep.parameters_before, rep.parameters_after, rep.notes
    structure = rep.structure
    if isinstance(ident, str):  # identify refused (or failed): no parameter goes out without its budget
        after, before = withheld(after, ident), withheld(before, ident)
        if structure is not None:
            structure = replace(structure, series_stiffness=withheld({"k_f": structure.series_stiffness},
                                                                     ident)["k_f"])
        return replace(rep, parameters_before=before, parameters_after=after, structure=structure,
                       unexplained=(*rep.unexplained, f"station identify refuses this run: {ident}"),
                       notes=(*notes, "parameters withheld: station identify refuses this run, so they have no "
                              "budget (measurement chain, masses); the effects above still describe the gap"),
                       wall_s=time.perf_counter() - t0)
    if ident is not None:
        before = ident[0]
        after = with_budget(after, ident[0], ident[1])
        notes = (*notes, BUDGET_NOTE)
        if structure is not None:  # the series stiffness carries the same systematic terms as k_f
            ks = with_budget({"k_f": structure.series_stiffness}, ident[0], ident[1])["k_f"]
            structure = replace(structure, series_stiffness=ks)
    else:
        notes = (*notes, "parameters_after: noise and model spread only (no budget: fewer than two steps)")
    after = stated_structure(after, structure, rep)
    return replace(rep, parameters_before=before, parameters_after=after, notes=notes, structure=structure,
                   wall_s=time.perf_counter() - t0)


def withheld(params: dict[str, Estimate], why: str) -> dict[str, Estimate]:
    """Every parameter withheld (not identifiable) with ``why``: what a refused identification leaves."""
    return {k: Estimate(None, None, e.unit, False, f"withheld: station identify refuses this run ({why})")
            for k, e in params.items()}


def stated_structure(after: dict[str, Estimate], structure: Any, rep: DiscrepancyResult) -> dict[str, Estimate]:
    """``after`` with the structure it rests on stated as ``identify`` states it: unless a coupling is
    named, k_f and b_f are those of a stiff coupling (Eq. 9), so k_f is the series stiffness of
    transducer and coupling, flagged 'conditional' with the range of k_f alone (``state_stiff``;
    unbounded above when the data do not determine k_f alone, ``structure``)."""
    if any(e.name == COUPLING_EFFECT for e in rep.effects):
        return after
    if structure is None:
        return state_stiff(after, None)
    rng = structure.k_f_alone_range
    return state_stiff(after, (structure.series_stiffness.value, None) if rng is None else rng)


BUDGET_NOTE = ("parameters_after: the standard uncertainties combine the model gap's own (noise, the spread "
               "of the models that fit) with the systematic terms of station identify's budget (measurement "
               "chain, masses, radius), scaled to the value")


def with_budget(after: dict[str, Estimate], ident: dict[str, Estimate], budget: UncertaintyBudget
                ) -> dict[str, Estimate]:
    """``after`` with the systematic terms of ``station identify``'s GUM budget (every source but its
    noise, the model gap's own noise and model spread taking its place, as identify's output-error
    method does with its noise term) added in quadrature, each scaled by value_after / value_identify
    (the chain and mass terms are relative to the value to first order)."""
    out = dict(after)
    for name, est in after.items():
        b, ref = budget.get(name), ident.get(name)
        if (b is None or ref is None or not est.identifiable or not ref.identifiable or not ref.value
                or est.value is None or est.std is None):
            continue
        scale = abs(est.value / ref.value)
        sys2 = sum((scale * c.std) ** 2 for c in b.contributions
                   if c.source != "noise" and c.std is not None and math.isfinite(c.std))
        out[name] = replace(est, std=math.sqrt(est.std**2 + sys2))
    return out


def run_context(rec: Recording, station: StationConfig | None = None) -> RunContext | str:
    """The limits and nominal steps a follow-up run must respect: the recording's own station
    configuration, or for an import its transducer (capacity, masses) with the rig's limits from its
    RUN.yaml (sinecal-csv v2 ``rig``); ``station`` (``--config``) supplies the rig's limits, plan
    times and chain instead.  Returns why nothing can be proposed when no limits are known."""
    from pydantic import ValidationError

    from station.config import parse_config

    steps = tuple((float(s.crank_frequency_hz), float(s.crank_radius_m)) for s in rec.steps if s.usable)
    try:
        cfg = parse_config(rec.config)
    except Exception:  # not a station configuration (an import): built from what the recording states
        cfg = None
    if cfg is not None and station is None:
        return RunContext(cfg, steps)
    rig = rec.config.get("rig") if isinstance(rec.config, dict) and rec.config.get("format") == "sinecal-csv" else None
    limits = station.rig.model_dump(exclude_none=True) if station is not None else rig
    if limits is None:
        why = ("no follow-up run proposed: the recording states no rig limits (crank frequency and radius "
               "ranges, peak force); an import carries them in RUN.yaml (sinecal-csv v2 `rig`), or give the "
               "rig's station configuration with --config")
        log.info("%s: %s", rec.path, why)
        return why
    end_mass = rec.end_mass_kg if rec.end_mass_kg is not None else None
    record = [(s.end_sample - s.start_sample) / rec.sample_rate_hz for s in rec.steps]
    doc: dict[str, Any] = {
        "transducer": {"id": rec.transducer_id, "capacity_N": rec.capacity_N,
                       "sensitivity_V_per_N": rec.sensitivity_V_per_N,
                       **({"end_mass_kg": end_mass} if end_mass else {})},
        "rig": {**{k: v for k, v in limits.items() if k in ("crank_frequency_hz", "crank_radius_m",
                                                           "peak_force_fraction", "acceleration_hz_per_s")},
                "top_mass_kg": rec.load_mass_kg, "adaption_mass_kg": 0.0},
        "plan": {"settle_s": station.plan.settle_s if station is not None else 1.0,
                 "record_s": float(np.median(record)) if record else 1.0,
                 "steps": [{"crank_frequency_hz": f, "crank_radius_m": r} for f, r in steps] or
                          [{"crank_frequency_hz": 1.0, "crank_radius_m": 1e-3}]}}
    if station is not None:
        doc["daq"] = station.daq.model_dump()
        doc["displacement_sensor"] = station.displacement_sensor.model_dump()
        doc["identification"] = station.identification.model_dump()
    else:  # an import's displacement chain is unknown: its range bounds no radius beyond the rig's
        r_max = float(limits.get("crank_radius_m", {}).get("max", 1.0))
        doc["displacement_sensor"] = {"gain_V_per_m": 10.0 * FILL / max(r_max, 1e-6)}
        doc["daq"] = {"displacement_range_V": 10.0}
    try:
        return RunContext(parse_config(doc), steps)
    except (ValidationError, StationError) as exc:
        why = f"no follow-up run proposed: the recording's limits are not usable ({str(exc).splitlines()[0]})"
        log.info("%s: %s", rec.path, why)
        return why


def _identify(rec: Recording) -> tuple[dict[str, Estimate], UncertaintyBudget] | str:
    """The base model's S, k_f, b_f as ``station identify --json`` reports them (frequency-domain fit
    of paper Eq. 9, ``station.ident``) and its uncertainty budget, or why identify gives none (its
    refusal, or its failure): the caller then withholds the parameters rather than report them with
    a noise-only uncertainty.  The values agree with the workflow's base fit; the uncertainties of a
    misfitting base model differ (identify inflates by the fundamental's chi^2/dof alone, which is
    the honest figure for k_f)."""
    from station.ident.identify import identify_recording

    try:
        res = identify_recording(rec, "fd", "sdof")
    except StationError as exc:  # a refusal (IdentificationRefused) or bad inputs: the same reason travels on
        log.info("%s: station identify refuses: %s", rec.path, exc)
        return str(exc)
    except (ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:
        log.warning("%s: station identify failed (%s): parameters withheld", rec.path, exc)
        return f"identification failed: {type(exc).__name__}: {exc}"
    out = {}
    for name, q in res.parameters.items():
        if name in ("S", "k_f", "b_f"):
            ok = q.identifiable and q.value is not None and q.std is not None
            out[name] = Estimate(float(q.value) if ok and q.value is not None else math.nan,
                                 float(q.std) if ok and q.std is not None else math.nan, q.unit, ok, q.reason)
    if len(out) != 3:
        return "identify gave no S, k_f and b_f"
    return out, res.budget


def gap_table(rep: DiscrepancyResult) -> list[tuple[str, list[float]]]:
    """Rows (stage, per-step gaps in V) from the base model through each added effect."""
    rows = [("base", list(rep.base_gap_steps))]
    rows += [(f"+ {e.name}", list(e.gap_steps_after)) for e in rep.effects]
    return rows


