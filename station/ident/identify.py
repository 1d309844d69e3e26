"""``identify_recording(rec, method, model)``: one entry point for every estimator.

Methods: 'fd' (sine fits per step -> H(f) -> linear start on 1/H -> weighted LM; default),
'oe' (time-domain output error), and the paper's 'pso', 'pso+' (Eq. 12-16) and 'rls' (Eq. 17)
on one step cut as in Section 5.1.  Models: 'sdof' (Eq. 9), 'coupled' (Eq. 8), and for the paper's
digital forms 'h2' (Eq. 11, maps to sdof) and 'h1' (Eq. 10, maps to coupled).
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from station.errors import BadInputError
from station.ident.fd.core import fd_fit as _fd_fit
from station.ident.fd.core import start_values
from station.ident.fd.core import start_values as _start
from station.ident.fd.identify import identify_fd
from station.ident.identifiability import Policy
from station.ident.inputs import IdentInputs, inputs_for
from station.ident.models import Model, SdofModel, make_model
from station.ident.names import METHODS, MODELS
from station.ident.oe import fit_oe
from station.ident.paper.protocol import PUBLISHED_SWARM, PaperProtocol, SwarmSize
from station.ident.response import frf as frfmod
from station.ident.response.checked import CheckedResponse, checked_response, measured_response
from station.ident.result import FitSummary, IdentificationResult, estimated_covariance, estimates
from station.ident.structure import structure_statement
from station.recording import Recording, write_result

__all__ = [
    "METHODS",
    "MODELS",
    "_fd_fit",
    "_start",
    "identify_fd",
    "identify_oe",
    "identify_recording",
    "measured_response",
    "model_for",
    "store_result",
]

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)
DEFAULT_POLICY = Policy()
DEFAULT_PROTOCOL = PaperProtocol()


def model_for(rec: Recording, key: str, inputs: IdentInputs | None = None) -> Model:
    """The model with the recording's masses (m_l load mass, m_e end mass; an unknown end mass is
    the assumed one of ``inputs``, 0 by default, and the result is then conditional on it)."""
    inputs = inputs or inputs_for(rec)
    if not inputs.end_mass_given and key in ("coupled", "h1"):
        raise BadInputError(f"{rec.path}: the coupled model needs the end mass, which is not recorded")
    return make_model(key, inputs.m_e, inputs.m_l)


def identify_oe(rec: Recording, model_key: str = "sdof", policy: Policy = DEFAULT_POLICY,
                inputs: IdentInputs | None = None) -> IdentificationResult:
    """Time-domain output error on the raw force samples, started from the FD estimate."""
    inputs = inputs or inputs_for(rec)
    cr = checked_response(rec, inputs)
    frf, sigs, notes = cr.frf, cr.sigs, []
    model = model_for(rec, "coupled" if model_key in ("coupled", "h1") else "sdof", inputs)
    fd = identify_fd(rec, model.key, policy, inputs=inputs)
    ok = np.array(fd.identifiability.identifiable) if fd.identifiability else np.ones(len(model.names), bool)
    sd = model_for(rec, "sdof", inputs)
    assert isinstance(sd, SdofModel)
    th0 = frfmod.fit_frf(frf, sd, start_values(frf, sd, cr.sign)).theta
    if model.key == "coupled":
        th0 = np.r_[th0, 10 * th0[1], 0.1 * th0[2]]
        if not ok[3]:
            model, ok, th0 = sd, ok[:3], th0[:3]
    fit = fit_oe(sigs, model, th0, free=ok)
    rep = fd.identifiability
    ident = tuple(bool(v) for v in ok)
    reasons = rep.reasons[: len(ident)] if rep else ("",) * len(ident)
    params = estimates(model.names, model.units, fit.theta, fit.cov, ident, reasons)
    covariance = estimated_covariance(params, model.names, fit.cov)  # correlations of the OE fit
    budget = {}
    for name, p in params.items():  # OE's own noise term, the systematic terms of the FD budget
        b = fd.budget.get(name)
        if p.identifiable and name in fd.parameters and not fd.parameter(name).identifiable:
            params[name] = fd.parameter(name)  # withheld by the FD result's structure (e.g. coupling_suspected)
            continue
        if b is None or not p.identifiable or p.std is None:
            continue
        c = {**b["contributions"], "noise": p.std}
        comb = float(np.sqrt(sum(v * v for v in c.values() if v is not None)))
        budget[name] = {**b, "contributions": c, "combined": comb}
        fdp = fd.parameter(name)
        params[name] = replace(p, std=comb, flag=fdp.flag, reason=fdp.reason if fdp.flag else p.reason)
    if covariance is not None:  # the same correlations at the combined standard uncertainties
        covariance = estimated_covariance(params, covariance.names, covariance.array)
    if len(params) < len(fd.parameters):
        params.update({n: p for n, p in fd.parameters.items() if n not in params})
        notes.append("k_c, b_c not identifiable: OE fit in the stiff-coupling limit (Eq. 9)")
    summary = FitSummary(fit.mse, tuple(float(v) for v in fit.residual_rms_V), float("nan"),
                         int(sum(s.t.size for s in sigs)))
    return IdentificationResult("oe", fd.model, params, summary, rep, tuple(notes),
                                {"offsets_V": fit.offsets_V.tolist()}, fd.checks, budget, fd.assumptions,
                                fd.determined, covariance)


def store_result(path: str | Path, res: IdentificationResult) -> str:
    """Store ``res`` beside the recording (its results folder, replacing an earlier result of the same
    method and model); returns where, relative to the recording's folder."""
    p = Path(path)
    return str(write_result(p, res.result_name, res.to_dict()).relative_to(p.parent))


def identify_recording(rec: Recording, method: str | None = None, model: str | None = None, *,
                       seed: int = 0, protocol: PaperProtocol = DEFAULT_PROTOCOL,
                       policy: Policy = DEFAULT_POLICY, response: CheckedResponse | None = None,
                       inputs: IdentInputs | None = None, swarm: SwarmSize = PUBLISHED_SWARM) -> IdentificationResult:
    """Identify the transducer from a recording.

    response: its checked H(f) if already computed (used by 'fd' and the paper's methods); inputs: masses and chain,
    default ``inputs_for(rec)``.  Default method: 'fd' (the efficient estimator for stepped-sine
    data, at the Cramér-Rao bound; with a single frequency it reports what is not identifiable);
    default model: 'auto' for fd (Eq. 9, Eq. 8 when the data demand and determine it), 'sdof' for
    oe, 'h2' for the paper's methods.  ``swarm``: another swarm size than Section 5.1's (pso, pso+)."""
    method = method or "fd"
    if method not in METHODS:
        raise BadInputError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
    if model is not None and model not in MODELS:
        raise BadInputError(f"unknown model {model!r}; expected one of {', '.join(MODELS)}")
    if method == "fd":
        return identify_fd(rec, model or "auto", policy, inputs=inputs, response=response)
    if method == "oe":
        return identify_oe(rec, model or "sdof", policy, inputs)
    form = {"sdof": "h2", "coupled": "h1"}.get(model or "h2", model or "h2")
    if method == "rls" and form != "h2":
        raise BadInputError("RLS (Eq. 17) is defined for H2 (Eq. 11) only")
    inputs = inputs or inputs_for(rec)
    from station.ident.paper.identify import identify_paper_method  # scipy.signal: only for the paper's methods

    # the same gate: only steps that passed, each at its measured frequency (a = -w^2 s, Eq. 2)
    cr = response or checked_response(rec, inputs)
    f_of = dict(zip(cr.used, cr.frf.f_hz, strict=True))
    checked = replace(rec, steps=[replace(st, crank_frequency_hz=float(f_of[st.index]))
                                  for st in rec.steps if st.index in f_of])
    res = identify_paper_method(checked, method, form, model_for(rec, form, inputs), seed=seed,
                                protocol=protocol, policy=policy)
    statement = structure_statement(form, form == "h2", inputs)
    statement["displacement_chain"]["note"] = (  # the swarm runs on the raw samples of one step
        "the paper's methods take the displacement samples as recorded: no chain correction is applied")
    budget = {n: {"contributions": {"noise": p.std}, "combined": p.std, "unit": p.unit}
              for n, p in res.parameters.items() if p.identifiable and p.std is not None}
    notes = (*res.notes, "budget: the noise of the step's steady-state gain and phase only; the paper's methods "
             "state no systematic terms")
    return replace(res, assumptions={**inputs.to_dict(), "structure": statement}, checks=tuple(cr.checks),
                   budget=budget, notes=notes)
