"""/runs/{id}/proposal: the follow-up run that would settle what the model-gap analysis of a run
left open (a tie between explanations, or a poorly determined k_f), ready to POST to /runs."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from station.api.deps import ArtifactsDep, Reader, RunDep
from station.api.routes import api_router
from station.api.routes.runs import E401, E404, E409, E422, E503
from station.run.request import RunRequest, StepSpec
from station.service.results import finite

router = api_router(prefix="/runs", tags=["runs"])
MAX_EFFECTS = 4  # the analysis the page and GET /runs/{id}/discrepancy show by default


class ProposedStepOut(BaseModel):
    model_config = ConfigDict(extra="forbid")

    crank_frequency_hz: float = Field(description="crank frequency in Hz")
    crank_radius_m: float = Field(description="crank radius in m (peak force within the limit under every "
                                  "tied model)")


class ProposalOut(BaseModel):
    """The analysis' ``proposal`` and the request that runs it (the run's own steps plus the added
    ones, so that one recording holds everything the analysis needs)."""

    model_config = ConfigDict(extra="allow")

    run: str
    proposal: dict[str, Any] | None = Field(
        description="reason, steps (added), run_steps, expected_information_gain (measure: delta_chi2 between "
                    "the tied models, or bits for a parameter), current, separates, pairs; null when nothing "
                    "needs settling")
    request: RunRequest | None = Field(description="body for POST /runs that makes the proposed run")
    note: str | None = Field(default=None, description="why nothing is proposed (null when there is a proposal)")


@router.get("/{run_id}/proposal", response_model=ProposalOut, dependencies=[Reader],
            responses={**E401, **E404, **E409, **E422, **E503},
            summary="The next run that settles a tie of the model-gap analysis")
async def run_proposal(run: RunDep, artifacts: ArtifactsDep) -> ProposalOut:
    """Part of the stored model-gap analysis (the default ``max_effects`` = 4; 404 until
    `POST /runs/{id}/discrepancy` has computed it).  ``request`` is ready to POST to /runs: same
    transducer and top mass, the steps of ``proposal.run_steps``."""
    out = finite(await artifacts.stored_discrepancy(run.id, MAX_EFFECTS))
    prop = out.get("proposal") if isinstance(out, dict) else None
    if not prop or not prop.get("run_steps"):
        note = out.get("proposal_note") if isinstance(out, dict) else None
        return ProposalOut(run=run.id, proposal=prop or None, request=None,
                           note=note if isinstance(note, str) else None)
    req = RunRequest(transducer_id=run.transducer_id, top_mass_kg=run.top_mass_kg,
                     steps=[StepSpec(crank_frequency_hz=s["crank_frequency_hz"], crank_radius_m=s["crank_radius_m"])
                            for s in prop["run_steps"]])
    return ProposalOut(run=run.id, proposal=prop, request=req)
