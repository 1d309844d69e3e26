"""``identify_campaign(recordings)``: one transducer, several top masses, identified jointly.

A single recording determines S (m_e + m_l), k_f / (m_e + m_l) and b_f / (m_e + m_l) only (Eq. 9);
national institutes separate the end mass m_e from the sensitivity S with several top masses.  Flow:

1. Inputs: every recording of the same transducer (``transducer_id``) and the same nominal
   sensitivity of the force signal (one S for all), each run once; otherwise refused.
2. H(f) per recording through the single-recording plausibility gate (``response.checked.checked_response``:
   steps left out, polarity), its load mass with its standard uncertainty and the measurement
   chain (``inputs.inputs_for``).
3. Joint weighted LM of (S, m_e, k_f, b_f) and the load masses (``jointfit``).
4. ``end_mass_separation``: from the combined covariance (noise, load masses, measurement chain),
   the standard uncertainty of m_e and the relative one of S.  Fewer than two distinct load masses (apart by more than
   ``distinct_sigma`` standard uncertainties), or a relative uncertainty of S above
   ``max_S_rel_std``: S and m_e are not separated; S, k_f, b_f are then given conditional on the
   stated end mass (with its uncertainty), or refused when none is stated.
5. ``same_transducer_model``: each recording's own Eq. 9 fit with m_e held at the campaign's value;
   S and k_f must agree across the masses (chi^2 homogeneity tests).
6. Budget (GUM, sources as the single-recording budget): noise, load_mass, end_mass (conditional
   case), chain_gain, chain_phase, chain_delay, radius; the combined standard uncertainty is that
   of the reported covariance.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from station.errors import BadInputError
from station.ident.assumptions import CampaignAssumptions, RunMass, StructureStatement
from station.ident.campaign import jointfit as jf
from station.ident.campaign.checks import (
    CampaignPolicy,
    campaign_budget,
    consistency,
    end_mass_plausibility,
    odd_one_out,
    own_fits,
    separation,
)
from station.ident.campaign.result import CampaignRecording, CampaignResult
from station.ident.inputs import IdentInputs, MassInput, inputs_for
from station.ident.models import SdofModel
from station.ident.response.checked import checked_response
from station.ident.response.frf import FrequencyResponse
from station.ident.response.gate import IdentificationRefused
from station.ident.result import Check, Estimate
from station.ident.structure import chain_corrected, coupling_bound, state_stiff, structure_statement
from station.ident.uncertainty import Covariance, DeterminedQuantity, ParameterBudget, UncertaintyBudget
from station.recording import Recording
from station.vocabulary import Flag, Severity

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)
RESULT_NAME = "campaign"  # stored as result "campaign" beside every recording of a campaign


class CampaignRefused(IdentificationRefused):
    """The recordings cannot be identified jointly; ``checks`` say why."""


def _param(name: str, unit: str, value: float | None, std: float | None, reason: str = "",
           flag: Flag = Flag.NONE) -> tuple[str, Estimate]:
    return name, Estimate(value, std, unit, value is not None, reason, flag)


def _load_mass(inp: IdentInputs) -> jf.MassPrior:
    return jf.MassPrior(inp.m_l, float(inp.load_mass.std or 0.0))


def check_inputs(recs: list[Recording]) -> None:
    """Refuse recordings that cannot be one transducer's campaign (different transducer ids or
    nominal sensitivities, one run given twice)."""
    if not recs:
        raise BadInputError("a campaign needs at least one recording")
    ids = {r.transducer_id for r in recs}
    if len(ids) > 1:
        per = ", ".join(f"{r.path.name}: {r.transducer_id!r}" for r in recs)
        raise CampaignRefused(f"recordings of different transducers cannot be identified jointly: {per}",
                              [Check("same_transducer", Severity.REFUSED, None, "different transducer ids",
                                     {"transducer_ids": sorted(ids)})])
    sens = np.array([r.sensitivity_V_per_N for r in recs])
    if np.ptp(sens) > 1e-9 * np.max(np.abs(sens)):
        per = ", ".join(f"{r.path.name}: {r.sensitivity_V_per_N:.6g} V/N" for r in recs)
        raise CampaignRefused("the nominal sensitivity of the force signal (bridge x conditioner gain) "
                              f"differs between the recordings, so one S cannot hold for all: {per}",
                              [Check("same_chain", Severity.REFUSED, None, "different nominal sensitivities",
                                     {"sensitivity_V_per_N": sens.tolist()})])
    runs = [r.run_id for r in recs]
    dup = sorted({x for x in runs if runs.count(x) > 1})
    if dup:
        raise CampaignRefused(f"run {', '.join(dup)} given more than once (it would count twice)", [])


def _stated_end_mass(inputs: list[IdentInputs], checks: list[Check]) -> jf.MassPrior | None:
    """The end mass the recordings state (with its standard uncertainty), None when none does."""
    given = [i.end_mass for i in inputs if i.end_mass_given]
    if not given:
        return None
    vals = [float(m.value or 0.0) for m in given]
    if len(given) < len(inputs) or np.ptp(vals) > 1e-9 * max(map(abs, vals)):
        checks.append(Check("end_mass_stated", Severity.WARNING, None, "the recordings state different end masses "
                            f"({', '.join(f'{v:g}' for v in vals)} kg); their mean is used where one is assumed",
                            {"end_mass_kg": vals}))
    return jf.MassPrior(float(np.mean(vals)), float(max(m.std or 0.0 for m in given)))


def _distinct(priors: list[jf.MassPrior], k: float) -> int:
    """Number of groups of load masses that differ by more than k combined standard uncertainties."""
    ms = sorted(priors, key=lambda p: p.value)
    groups = 1
    for a, b in itertools.pairwise(ms):
        if abs(b.value - a.value) > k * np.hypot(a.std, b.std) + 1e-12 * b.value:
            groups += 1
    return groups




def _determined(recs: list[Recording], priors: list[jf.MassPrior], own: list[FloatArray],
                m_e: float) -> dict[str, tuple[DeterminedQuantity, ...]]:
    """What each recording determines whatever the end mass (names as the single-recording result's
    ``determined``, one entry per recording): S M in V s^2/m and the loaded natural frequency
    f_0 = sqrt(k_f / M) / (2 pi) in Hz, from its own fit (invariant to the m_e held)."""
    sm: list[DeterminedQuantity] = []
    fn: list[DeterminedQuantity] = []
    for r, pr, o in zip(recs, priors, own, strict=True):
        M = m_e + pr.value
        sm.append(DeterminedQuantity(float(o[0] * M), "V*s^2/m", ParameterBudget.of({}, float(o[3] * M), "V*s^2/m"),
                                     run_id=r.run_id))
        ok = o[1] > 0 and M > 0  # a fit gone wrong (e.g. a mistyped mass) has no natural frequency
        f0 = float(np.sqrt(o[1] / M) / (2 * np.pi)) if ok else None
        u = float(f0 * o[4] / (2 * o[1])) if f0 else float("nan")
        fn.append(DeterminedQuantity(f0, "Hz", ParameterBudget.of({}, u, "Hz"), run_id=r.run_id))
    return {"S_times_M": tuple(sm), "natural_frequency_hz": tuple(fn)}


def identify_campaign(recs: list[Recording], policy: CampaignPolicy | None = None, *,
                      assumed_end_mass_kg: float | None = None,
                      assumed_end_mass_std_kg: float | None = None) -> CampaignResult:
    """Identify S, m_e, k_f, b_f jointly from recordings of one transducer with different top masses
    (module docstring).  Raises CampaignRefused for recordings that cannot be one campaign.

    assumed_end_mass_kg (kg; with its standard uncertainty assumed_end_mass_std_kg, else none): for
    recordings that state no end mass; used where the masses cannot separate S from m_e (the results
    are then conditional on it) and compared with the campaign's m_e where they can."""
    policy = policy or CampaignPolicy()
    check_inputs(recs)
    if assumed_end_mass_kg is not None:
        stating = [r.path.name for r in recs if r.end_mass_kg is not None]
        if stating:
            raise BadInputError(f"{', '.join(stating)}: the recording states the end mass; an assumed one is only "
                                "for recordings that give none")
        if assumed_end_mass_kg <= 0 or (assumed_end_mass_std_kg is not None and assumed_end_mass_std_kg < 0):
            raise BadInputError(f"an assumed end mass > 0 kg (std >= 0 kg) expected, got {assumed_end_mass_kg!r} kg, "
                                f"std {assumed_end_mass_std_kg!r}")
    checks: list[Check] = []
    frfs, used, inputs, signs = [], [], [], set()
    for r in recs:
        inp = inputs_for(r, assumed_end_mass_kg=assumed_end_mass_kg,
                         assumed_end_mass_std_kg=assumed_end_mass_std_kg)
        try:
            cr = checked_response(r, inp)
        except IdentificationRefused as exc:
            raise CampaignRefused(f"{r.path.name}: {exc}", [_tagged(c, r) for c in exc.checks]) from None
        checks += [_tagged(c, r) for c in cr.checks if c.severity != "info"]
        frfs.append(chain_corrected(cr.frf, inp.chain))
        used.append(tuple(cr.used))
        inputs.append(inp)
        signs.add(cr.sign)
    if len(signs) > 1:
        raise CampaignRefused("the polarity of the force signal differs between the recordings (S changes "
                              "sign): check the wiring or the conditioner setting before a joint fit", checks)
    chain = inputs[0].chain
    if any(i.chain != chain for i in inputs):
        checks.append(Check("same_chain", Severity.WARNING, None, "the recordings state different measurement chains; "
                            f"the first one's ({recs[0].path.name}) is used for the budget", {}))
    priors = [_load_mass(i) for i in inputs]
    stated = _stated_end_mass(inputs, checks)
    if stated is None and assumed_end_mass_kg is not None:  # assumed without an uncertainty: held exactly
        stated = jf.MassPrior(assumed_end_mass_kg, 0.0)
    n_distinct = _distinct(priors, policy.distinct_sigma)
    th0 = jf.start_values(frfs, priors, stated.value if stated else 0.0)
    sep: Check
    if n_distinct >= 2:
        fit = jf.fit_joint(frfs, priors, th0)
        cov, budget = campaign_budget(frfs, priors, fit, True, chain, None)
        sep = separation(fit, cov, priors, policy)
    else:
        sep = Check("end_mass_separation", Severity.REFUSED, None,
                      f"{len(recs)} recording(s) with {n_distinct} distinct top mass: the data determine "
                      "S (m_e + m_l) and the loaded natural frequency only, not S and m_e separately; "
                      "record the transducer with at least two different top masses",
                      {"load_masses_kg": [p.value for p in priors], "distinct": n_distinct})
    checks.append(sep)
    separated = sep.severity != "refused"
    if not separated:
        th0[1] = stated.value if stated else 0.0
        fit = jf.fit_joint(frfs, priors, th0, free_m_e=False, m_e_prior=stated)
        cov, budget = campaign_budget(frfs, priors, fit, False, chain, stated)
    own = own_fits(frfs, priors, fit.theta)
    cons = consistency(recs, own, policy)
    if cons is not None and cons.severity != "info":
        odd = odd_one_out(frfs, priors, recs, fit.theta)
        if odd is not None:
            cons = replace(cons, message=f"{cons.message}; without {odd[0]} the others fit with chi2/dof "
                           f"{odd[1]:.3g}", values={**cons.values, "odd_one_out": odd[0],
                                                     "chi2_per_dof_without": odd[1]})
    if cons is not None:
        checks.append(cons)
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    if separated:
        checks += end_mass_plausibility(fit, float(sd[1]), stated, n_distinct)
    notes: list[str] = []
    if fit.inflated:
        notes.append(f"chi2/dof = {fit.chi2_per_dof:.3g}: the noise terms inflated by sqrt(chi2/dof)")
        checks.append(Check("model_misfit", Severity.WARNING, None, f"Eq. 9 with one S, m_e, k_f, b_f misfits the "
                            f"recordings: chi2/dof = {fit.chi2_per_dof:.3g} on {fit.dof}; the noise terms are "
                            "inflated by sqrt(chi2/dof)", {"chi2_per_dof": fit.chi2_per_dof, "dof": fit.dof}))
    refused_model = cons is not None and cons.severity == "refused"
    if refused_model:
        status = "refused"
        params = dict(_param(n, u, None, None, cons.message if cons else "") for n, u in zip(jf.NAMES, jf.UNITS,
                                                                                            strict=True))
    elif separated:
        status = "separated"
        flag = Flag.POORLY_DETERMINED if sep.severity == "warning" else Flag.NONE
        params = dict(_param(n, u, float(fit.theta[i]), float(sd[i]), sep.message if flag and i < 2 else "",
                              flag if i < 2 else Flag.NONE)
                      for i, (n, u) in enumerate(zip(jf.NAMES, jf.UNITS, strict=True)))
    elif stated is not None:
        status = "conditional"
        src = inputs[0].end_mass.source
        why = (f"given on the {'assumed' if src == 'assumed' else 'stated'} end mass m_e = {stated.value:g} kg "
               + (f"(std {stated.std:.2g} kg, propagated)" if stated.std > 0 else "(no uncertainty: not propagated)")
               + ": the top masses do not separate S from m_e")
        params = dict(_param(n, u, None, None, sep.message) if i == 1 else
                       _param(n, u, float(fit.theta[i]), float(sd[i]), why, Flag.CONDITIONAL)
                       for i, (n, u) in enumerate(zip(jf.NAMES, jf.UNITS, strict=True)))
    else:
        status = "refused"
        why = sep.message + "; no end mass is stated, so S, k_f and b_f are not given (see determined)"
        params = dict(_param(n, u, None, None, why) for n, u in zip(jf.NAMES, jf.UNITS, strict=True))
    if status == "refused":
        cov = np.zeros((4, 4))
        budget = UncertaintyBudget()
    rows = tuple(CampaignRecording(str(r.path), r.run_id, pr.value, pr.std, float(fit.load_mass[k]),
                                   float(fit.load_mass_std[k]), used[k],
                                   (float(frfs[k].f_hz.min()), float(frfs[k].f_hz.max())),
                                   float(fit.chi2_by_recording[k]), (float(own[k][0]), float(own[k][3])),
                                   (float(own[k][1]), float(own[k][4])))
                 for k, (r, pr) in enumerate(zip(recs, priors, strict=True)))
    me = (MassInput(float(fit.theta[1]), float(sd[1]), "campaign") if status == "separated"
          else MassInput(stated.value, stated.std, inputs[0].end_mass.source) if stated else None)
    structure = _structure(frfs, priors, fit.theta, fit.chi2_per_dof if fit.inflated else 1.0, inputs[0])
    params = state_stiff(params, None if structure.coupling is None else structure.coupling.k_f_alone_range,
                         "the recordings")
    masses = tuple(RunMass(r.run_id, p.value, p.std) for r, p in zip(recs, priors, strict=True))
    assumptions = CampaignAssumptions("Eq. 9 (stiff coupling), one S, m_e, k_f, b_f for every recording", me,
                                      masses, chain.model_dump(), structure)
    log.info("campaign of %d recordings: %s", len(recs), status)
    covariance = Covariance.of(jf.NAMES, jf.UNITS, cov)
    return CampaignResult(status, recs[0].transducer_id, params, covariance, rows, fit.chi2, fit.dof, fit.inflated,
                          tuple(checks), budget, assumptions, _determined(recs, priors, own, float(fit.theta[1])),
                          tuple(notes))


def _structure(frfs: list[FrequencyResponse], priors: list[jf.MassPrior], theta: FloatArray, birge: float,
               inputs: IdentInputs) -> StructureStatement:
    """The structure the joint fit rests on (Eq. 9, the displacement chain) and the softest coupling
    the best single recording cannot tell from a stiff one, with the range of k_f alone that follows
    (the joint k_f is the series stiffness of transducer and coupling, ``structure``)."""
    bounds = [b for f, pr in zip(frfs, priors, strict=True)
              if (b := coupling_bound(f, SdofModel(max(float(theta[1]), 0.0), pr.value),
                                      np.array([theta[0], theta[2], theta[3]]), birge)) is not None]
    best = max(bounds, key=lambda b: np.inf if b.k_c_min is None else b.k_c_min) if bounds else None
    return structure_statement("sdof", True, inputs, best)


def _tagged(c: Check, rec: Recording) -> Check:
    """A recording's own check, its file name added to the values."""
    return replace(c, values={**c.values, "recording": rec.path.name})
