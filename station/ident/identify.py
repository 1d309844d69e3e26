"""``identify_recording(rec, method, model)``: one entry point for every estimator.

Methods: 'fd' (sine fits per step -> H(f) -> linear start on 1/H -> weighted LM; default),
'oe' (time-domain output error), and the paper's 'pso', 'pso+' (Eq. 12-16) and 'rls' (Eq. 17)
on one step cut as in Section 5.1.  Models: 'sdof' (Eq. 9), 'coupled' (Eq. 8), and for the paper's
digital forms 'h2' (Eq. 11, maps to sdof) and 'h1' (Eq. 10, maps to coupled).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from station.errors import BadInputError
from station.ident.assumptions import Assumptions
from station.ident.fd.identify import identify_fd
from station.ident.identifiability import Policy
from station.ident.inputs import IdentInputs, inputs_for, model_for
from station.ident.names import METHODS, MODELS
from station.ident.oe import identify_oe
from station.ident.paper.protocol import PUBLISHED_SWARM, PaperProtocol, SwarmSize
from station.ident.paper.rls_uncertainty import RLS_BUDGET_NOTE, rls_assumptions
from station.ident.response.checked import CheckedResponse, checked_response
from station.ident.result import IdentificationResult
from station.ident.structure import structure_statement
from station.recording import Recording, write_result

DEFAULT_POLICY = Policy()
DEFAULT_PROTOCOL = PaperProtocol()


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
                                protocol=protocol, policy=policy, swarm=swarm)
    statement = structure_statement(form, form == "h2", inputs)
    statement = replace(statement, displacement_chain={  # the swarm runs on the raw samples of one step
        **statement.displacement_chain,
        "note": "the paper's methods take the displacement samples as recorded: no chain correction is applied"})
    notes = (*res.notes, RLS_BUDGET_NOTE if method == "rls" else
             "budget: the noise of the step's steady-state gain and phase only (the swarm states no "
             "uncertainty of the parameters one frequency leaves undetermined, so a parameter whose "
             "uncertainty rests on them is withheld); the paper's methods state no systematic terms")
    rls = rls_assumptions() if method == "rls" else None
    return replace(res, assumptions=Assumptions.of(inputs, statement, rls),
                   checks=tuple(cr.checks),
                   notes=notes)
