"""/runs: start, list, follow, abort runs; their results, plots, report, recording, discrepancy."""

from __future__ import annotations

import json
from collections.abc import AsyncIterable
from pathlib import Path as PathLib
from typing import Annotated, Any

from fastapi import Path, Query, Request, Response, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, StreamingResponse
from fastapi.sse import EventSourceResponse, ServerSentEvent

from station.api.deps import ArtifactsDep, ManagerDep, Operator, Reader, RunDep, RunsDep
from station.api.problems import MEDIA_TYPE, Refusal
from station.api.routes import api_router
from station.api.schemas import (
    AbortOut,
    DiscrepancyOut,
    ErrorOut,
    MethodStateOut,
    PlannedStepOut,
    RunAccepted,
    RunLinks,
    RunList,
    RunResults,
    RunState,
    RunStatus,
    ValidationErrorOut,
    utc,
)
from station.errors import LimitError
from station.lab.register import RegisterError, UnknownEntryError
from station.lab.store import FINAL_STATES, RunRow
from station.report.names import PLOT_NAMES
from station.run.methods import SETTLED, MethodOutcome
from station.run.request import RunRequest
from station.service.artifacts import Artifacts
from station.service.manager import RunStateError
from station.service.results import load_results

BINARY = {"type": "string", "format": "binary"}  # a file's bytes, as OpenAPI declares them

router = api_router(prefix="/runs", tags=["runs"])
Responses = dict[int | str, dict[str, Any]]  # a route's documented responses, by status

E401: Responses = {401: {"model": ErrorOut, "description": "bearer token missing or wrong"}}
E403: Responses = {403: {"model": ErrorOut, "description": "the role may not do this, or cross-site"}}
E404: Responses = {404: {"model": ErrorOut, "description": "no such run"}}
E409: Responses = {409: {"model": ErrorOut, "description": "the run is not in a state that allows this"}}
E422: Responses = {422: {"model": ValidationErrorOut,
                          "description": "invalid or unsafe parameters; `loc` names the field"}}
E503: Responses = {503: {"model": ErrorOut, "description": "the recording or the rig cannot be reached right now"}}
BODY_ERRORS: Responses = {  # what the body guard answers on any POST that carries a body (api/guard.py)
    413: {"model": ErrorOut, "description": "request body larger than service.max_body_bytes (not read)"},
    415: {"model": ErrorOut, "description": "request body that is not JSON by its Content-Type (not read)"}}


def _json(status: int, description: str, schema: str = "Problem") -> dict[int | str, dict[str, Any]]:
    """An error response documented on a route whose success is not JSON (SSE, PNG, HTML): problem
    details (the OpenAPI document declares every 4xx/5xx so, station/api/problems.py)."""
    return {status: {"description": description,
                     "content": {MEDIA_TYPE: {"schema": {"$ref": f"#/components/schemas/{schema}"}}}}}


NON_JSON_ERRORS = {**_json(401, "bearer token missing or wrong"), **_json(404, "no such run"),
                   **_json(409, "the run is not in a state that allows this"),
                   **_json(422, "invalid path or query parameter", "ValidationProblem"),
                   **_json(503, "the recording cannot be read right now")}


def links(run_id: str) -> RunLinks:
    base = f"/runs/{run_id}"
    return RunLinks(self=base, events=f"{base}/events", results=f"{base}/results",
                    recording=f"{base}/recording", abort=f"{base}/abort")


def status_of(row: RunRow, methods: list[MethodOutcome] | None = None) -> RunStatus:
    steps = [PlannedStepOut(**{k: s[k] for k in PlannedStepOut.model_fields}) for s in row.plan.get("steps", [])]
    return RunStatus(id=row.id, state=row.state, transducer_id=row.transducer_id,
                     top_mass_kg=row.top_mass_kg, created=utc(row.created), started=utc(row.started),
                     ended=utc(row.ended), current_step=row.step, n_steps=row.n_steps, step_state=row.step_state,
                     progress=min(1.0, max(0.0, row.fraction)), samples=row.samples,
                     lost_samples=row.lost_samples, message=row.message, reason=row.reason,
                     recording=row.recording, steps=steps, links=links(row.id),
                     methods=[MethodStateOut.model_validate(o.to_dict()) for o in methods or ()], operator=row.operator,
                     standards=[s.get("id", "") for s in json.loads(row.standards_json or "[]")])


@router.post("", status_code=status.HTTP_202_ACCEPTED, response_model=RunAccepted,
             responses={**E401, **E403, **E422, **BODY_ERRORS,
                        409: {"model": ErrorOut, "description": "another run holds the rig"},
                        503: {"model": ErrorOut, "description": "the rig is not connected"}},
             summary="Start a calibration run")
async def start_run(body: RunRequest, runs: RunsDep, response: Response, who: Operator) -> RunAccepted:
    """Check the request against the register (the transducer, any registered one; the reference
    standards, named or those in use, none past its due date) and the rig and transducer limits,
    then queue it on the rig.  Step fields other than frequency and radius default to the
    configured plan's.  Steps are numbered from 0 in `loc` (as in the body's list)."""
    try:
        row = await runs.submit(body, who.name)
    except LimitError as exc:  # the field to change: in the request body, or the station's configuration
        raise RequestValidationError([{"type": "limit_error", "loc": exc.loc, "msg": str(exc),
                                       "input": exc.value}]) from None
    except RegisterError as exc:
        field = "transducer_id" if isinstance(exc, UnknownEntryError) and "transducer" in str(exc) else "standards"
        raise RequestValidationError([{"type": "register_error", "loc": ["body", field], "msg": str(exc),
                                       "input": getattr(body, field)}]) from None
    response.headers["Location"] = f"/runs/{row.id}"
    return RunAccepted(id=row.id, state=row.state, links=links(row.id))


@router.get("", response_model=RunList, dependencies=[Reader], responses={**E401, **E422},
            summary="List runs, newest first")
async def list_runs(runs: RunsDep, manager: ManagerDep, limit: Annotated[int, Query(ge=1, le=1000)] = 100,
                    state: Annotated[list[RunState] | None, Query()] = None) -> RunList:
    rows = await runs.list_runs(limit=limit, states=list(state) if state else None)
    return RunList(count=len(rows), runs=[status_of(r, manager.jobs.outcomes.get(r.id)) for r in rows])


@router.get("/{run_id}", response_model=RunStatus, dependencies=[Reader], responses={**E401, **E404, **E422},
            summary="A run's state and progress")
async def get_run(run: RunDep, manager: ManagerDep) -> RunStatus:
    return status_of(run, manager.jobs.outcomes.get(run.id))


@router.get("/{run_id}/events", response_class=EventSourceResponse, dependencies=[Reader],
            responses=NON_JSON_ERRORS, summary="Live progress (server-sent events)")
async def run_events(run: RunDep, manager: ManagerDep, runs: RunsDep,
                     request: Request) -> AsyncIterable[ServerSentEvent]:
    """Event `status` (data: the RunStatus JSON) on every change, at most a few per second; event
    `result` (data: the MethodStateOut JSON) when a listed identification has its outcome, the
    primary's first (the run is then completed and its results readable), the others as they
    follow; event `end` with the final status once the run is completed (and every listed method has
    its outcome), aborted, failed or interrupted."""
    run_id = run.id
    version = -1
    last: dict[str, Any] | None = None
    told: set[tuple[str, str]] = set()  # methods whose outcome was sent
    while True:
        cur = manager.changes.version(run_id)
        st = status_of(await runs.get(run_id), manager.jobs.outcomes.get(run_id))
        data = st.model_dump(mode="json")
        if data != last:
            last = data
            yield ServerSentEvent(data=data, event="status", id=str(cur))
            for m in data["methods"]:
                if m["status"] in SETTLED and (m["method"], m["model"]) not in told:
                    told.add((m["method"], m["model"]))
                    yield ServerSentEvent(data=m, event="result", id=str(cur))
        if st.state in FINAL_STATES and not manager.jobs.identifying(run_id):
            yield ServerSentEvent(data=data, event="end", id=str(cur))
            return
        if manager.closing.is_set() or await request.is_disconnected():
            return
        version = cur
        await manager.changes.wait(run_id, version, 10.0)


@router.get("/{run_id}/results", response_model=RunResults, dependencies=[Reader],
            responses={**E401, **E404, **E409, **E422, **E503}, summary="Identified parameters, H(f), fit")
async def run_results(run: RunDep, artifacts: ArtifactsDep) -> RunResults:
    if run.state != "completed" or not run.result_name:
        raise RunStateError(f"run {run.id} is {run.state}: results exist once a run is completed"
                            + (f" ({run.reason})" if run.reason else ""))
    data = await artifacts.read_file(run.id, lambda p: load_results(p, run.result_name or ""))
    base = f"/runs/{run.id}"
    plots = {n: f"{base}/plots/{n}.png" for n in PLOT_NAMES}
    return RunResults(id=run.id, state=run.state, recording=run.recording or "",
                      plots=plots, report=f"{base}/report",
                      discrepancy=f"{base}/discrepancy", lost_samples=run.lost_samples, **data)


@router.get("/{run_id}/plots/{name}.png", response_class=Response, dependencies=[Reader],
            responses={200: {"content": {"image/png": {"schema": BINARY}}, "description": "PNG image"},
                       **NON_JSON_ERRORS},
            summary="A plot: bode, timefit, residuals, convergence, ...")
async def run_plot(run: RunDep, artifacts: ArtifactsDep,
                   name: Annotated[str, Path(pattern=r"^[A-Za-z0-9_\-]{1,64}$")]) -> Response:
    png = await artifacts.plot(run.id, name)
    if png is None:
        raise Refusal(404, "not-found", f"no plot {name!r}; available: {', '.join(PLOT_NAMES)}")
    return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=3600"})


@router.get("/{run_id}/report", response_class=HTMLResponse, dependencies=[Reader],
            responses={200: {"content": {"text/html": {"schema": {"type": "string"}}}}, **NON_JSON_ERRORS},
            summary="The calibration report (HTML)")
async def run_report(run: RunDep, artifacts: ArtifactsDep) -> HTMLResponse:
    return HTMLResponse(await artifacts.report(run.id))


@router.get("/{run_id}/report.pdf", response_class=Response, dependencies=[Reader],
            responses={200: {"content": {"application/pdf": {"schema": BINARY}}, "description": "PDF"},
                       **NON_JSON_ERRORS},
            summary="The calibration report as PDF (the same page through the HTML-to-PDF engine)")
async def run_report_pdf(run: RunDep, artifacts: ArtifactsDep) -> Response:
    return Response(await artifacts.report_pdf(run.id), media_type="application/pdf")


def ended_recording(run: RunRow, artifacts: Artifacts) -> PathLib:
    """The recording of a run that has ended (RunStateError while it is being written)."""
    if run.state not in FINAL_STATES:
        raise RunStateError(f"run {run.id} is {run.state}: its recording is still being written; "
                            "download it once the run has ended")
    return artifacts.recording_path(run)


@router.get("/{run_id}/recording", response_class=StreamingResponse, dependencies=[Reader],
            responses={200: {"content": {"application/x-hdf5": {"schema": BINARY}},
                             "description": "the HDF5 recording"},
                       **NON_JSON_ERRORS},
            summary="Download the HDF5 recording")
async def run_recording(run: RunDep, artifacts: ArtifactsDep) -> StreamingResponse:
    ended_recording(run, artifacts)
    path = await artifacts.checked_path(run.id)  # compared with the audit chain before the first byte
    return StreamingResponse(artifacts.stream_file(run.id), media_type="application/x-hdf5",
                             headers={"Content-Disposition": f'attachment; filename="{path.name}"',
                                      "Content-Length": str(path.stat().st_size)})


MaxEffects = Annotated[int, Query(ge=0, le=8, description="catalogue effects added at most")]
E404_ANALYSIS: Responses = {404: {"model": ErrorOut, "description": "no such run, or no analysis with this "
                                  "max_effects stored yet (the message names the POST that computes it)"}}


@router.get("/{run_id}/discrepancy", response_model=DiscrepancyOut, dependencies=[Reader],
            responses={**E401, **E404_ANALYSIS, **E409, **E422, **E503},
            summary="The stored model-gap analysis of the run")
async def run_discrepancy(run: RunDep, artifacts: ArtifactsDep, max_effects: MaxEffects = 4) -> DiscrepancyOut:
    """Which catalogue effect the measurement shows that the model lacks, as stored beside the
    recording by `POST /runs/{id}/discrepancy` or `station discrepancy --save`.  Reads only."""
    from station.service.results import finite

    return DiscrepancyOut.model_validate(finite(await artifacts.stored_discrepancy(run.id, max_effects)))


@router.post("/{run_id}/discrepancy", response_model=DiscrepancyOut,
             responses={**E401, **E403, **E404, **E409, **E422, **E503, **BODY_ERRORS},
             summary="Compute and store the model-gap analysis of the run")
async def compute_discrepancy(run: RunDep, artifacts: ArtifactsDep, manager: ManagerDep, who: Operator,
                              max_effects: MaxEffects = 4) -> DiscrepancyOut:
    """Runs the analysis in a worker process and stores it beside the recording (replacing an
    earlier one), where `GET`, the proposal and the report read it; the audit trail records who."""
    from station.service.results import finite

    out = await artifacts.discrepancy(run.id, max_effects, who.name)
    return DiscrepancyOut.model_validate(finite(out))


@router.post("/{run_id}/abort", status_code=status.HTTP_202_ACCEPTED, response_model=AbortOut,
             responses={**E401, **E403, **E404, **E409, **E422, **BODY_ERRORS}, summary="Abort a run")
async def abort_run(run: RunDep, runs: RunsDep, who: Operator) -> AbortOut:
    """The crank ramps down, the recording is closed with the reason; the run ends `aborted`."""
    row = await runs.abort(run.id, f"aborted by {who.name}", who.name)
    return AbortOut(id=row.id, state=row.state, detail="abort requested; the crank ramps down")
