"""A run's results as tables for a spreadsheet: parameters and S_dyn(f) as CSV and as an Excel
workbook (``station.report.export``)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Path, Response

from station.api.deps import ArtifactsDep, Reader, RunDep
from station.api.routes.runs import BINARY, NON_JSON_ERRORS
from station.report.export import MEDIA_TYPES, export_bytes
from station.service.manager import RunStateError

router = APIRouter(prefix="/runs", tags=["runs"])

ExportName = Literal["parameters.csv", "sdyn.csv", "results.xlsx"]


@router.get("/{run_id}/export/{name}", response_class=Response, dependencies=[Reader],
            responses={200: {"description": "parameters.csv: the identified parameters with their standard "
                             "uncertainties and units; sdyn.csv: S_dyn(f) of the measured steps with u and U "
                             "(k = 2), units in the headers; results.xlsx: both as sheets of a workbook",
                             "content": {"text/csv": {"schema": BINARY}, MEDIA_TYPES["results.xlsx"]: {
                                 "schema": BINARY}}},
                       **NON_JSON_ERRORS},
            summary="The results as CSV or an Excel workbook")
async def run_export(run: RunDep, artifacts: ArtifactsDep,
                     name: Annotated[ExportName, Path(description="which table, and its format")]) -> Response:
    if run.state != "completed":
        raise RunStateError(f"run {run.id} is {run.state}: its results can be exported once it is completed")
    path = artifacts.recording_path(run)
    data = await artifacts.read_file(run.id, lambda p: export_bytes(p, name))
    return Response(data, media_type=MEDIA_TYPES[name],
                    headers={"Content-Disposition": f'attachment; filename="{path.stem}.{name}"'})
