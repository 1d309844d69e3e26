"""/campaigns: several completed runs of one transducer with different top masses, identified
jointly (S, m_e, k_f, b_f; ``station.ident.campaign.identify``)."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from fastapi.exceptions import RequestValidationError

from station.api.campaign_schemas import CampaignOut, CampaignRequest
from station.api.deps import ManagerDep, Operator
from station.api.routes import api_router
from station.api.routes.runs import BODY_ERRORS, E403
from station.api.schemas import ErrorOut, ValidationErrorOut
from station.lab import audit
from station.recording import write_result
from station.service.results import finite

router = api_router(prefix="/campaigns", tags=["campaigns"])


@router.post("", response_model=CampaignOut,
             responses={**BODY_ERRORS, **E403, 401: {"model": ErrorOut, "description": "bearer token missing or wrong"},
                        404: {"model": ErrorOut, "description": "no such run"},
                        409: {"model": ErrorOut, "description": "a run is not completed"},
                        422: {"model": ValidationErrorOut,
                              "description": "invalid request, or runs that cannot be one campaign (different "
                                             "transducers or nominal sensitivities, a run twice, mixed polarity)"},
                        503: {"model": ErrorOut, "description": "a recording cannot be read right now"}},
             summary="Identify runs with different top masses jointly (S, end mass m_e, k_f, b_f)")
async def identify_campaign_route(body: CampaignRequest, manager: ManagerDep, who: Operator) -> CampaignOut:
    """Reads each run's recording and fits Eq. 9 to all of them at once, the end mass m_e a
    parameter, in a worker process (like every computation of the station).  With `store` the
    result is also stored beside every run's recording (`<run>.results/results.campaign.h5`), where
    the run's report shows it.  Top masses too alike to separate S from m_e give status
    `conditional` or `refused` with the named check `end_mass_separation`, not an error."""
    out = await manager.artifacts.campaign(list(body.runs))
    if "refused" in out:
        raise RequestValidationError([{"type": "campaign_refused", "loc": ["body", "runs"], "msg": out["refused"],
                                       "input": list(body.runs)}])
    payload: dict[str, Any] = out["result"]
    data: dict[str, Any] = finite(payload)
    for r in data["recordings"]:
        r["path"] = Path(r["path"]).name  # never a server path
    stored = None
    if body.store:
        # the result's name, imported only to store it: the identification (scipy) stays out of the web
        # process for a refused or unknown run (it is computed in the worker)
        from station.ident.campaign.identify import RESULT_NAME

        runs = list(body.runs)
        for run_id in runs:  # each written and vouched for in the audit trail under its recording's lock
            row = await manager.runs.get(run_id)
            path = manager.artifacts.recording_path(row)
            async with manager.artifacts.file_lock(run_id):
                await asyncio.to_thread(write_result, path, RESULT_NAME, payload)
                await manager.artifacts.seal(row, who.name, audit.RESULT_STORED, {"kind": "campaign", "runs": runs})
        stored = f"<run>.results/results.{RESULT_NAME}.h5"
    return CampaignOut.model_validate({**data, "runs": list(body.runs), "stored_as": stored})
