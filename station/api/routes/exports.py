"""A run's results as tables for a spreadsheet: parameters and S_dyn(f) as CSV and as an Excel
workbook (``station.report.export``); the recording with its results and certificates as one ZIP
archive with a manifest of hashes (``station.recording.archive``)."""

from __future__ import annotations

from pathlib import Path as PathLib
from typing import Annotated, Literal

from fastapi import Path, Response

from station.api.deps import ArtifactsDep, Reader, RunDep
from station.api.routes import api_router
from station.api.routes.runs import BINARY, NON_JSON_ERRORS, ended_recording
from station.report.names import EXPORT_MEDIA_TYPES
from station.service.manager import RunStateError

router = api_router(prefix="/runs", tags=["runs"])

ExportName = Literal["parameters.csv", "sdyn.csv", "results.xlsx"]


@router.get("/{run_id}/export/{name}", response_class=Response, dependencies=[Reader],
            responses={200: {"description": "parameters.csv: the identified parameters with their standard "
                             "uncertainties and units; sdyn.csv: S_dyn(f) of the measured steps with u and U "
                             "(k = 2), units in the headers; results.xlsx: both as sheets of a workbook",
                             "content": {"text/csv": {"schema": BINARY}, EXPORT_MEDIA_TYPES["results.xlsx"]: {
                                 "schema": BINARY}}},
                       **NON_JSON_ERRORS},
            summary="The results as CSV or an Excel workbook")
async def run_export(run: RunDep, artifacts: ArtifactsDep,
                     name: Annotated[ExportName, Path(description="which table, and its format")]) -> Response:
    if run.state != "completed":
        raise RunStateError(f"run {run.id} is {run.state}: its results can be exported once it is completed")
    path = artifacts.recording_path(run)
    data = await artifacts.read_file(run.id, lambda p: _export(p, name))
    return Response(data, media_type=EXPORT_MEDIA_TYPES[name],
                    headers={"Content-Disposition": f'attachment; filename="{path.stem}.{name}"'})


def _export(path: PathLib, name: str) -> bytes:
    """Export ``name`` of the recording at ``path`` (in a thread: the report's modules, which import
    the identification's and scipy, are loaded on the first export, not with the daemon)."""
    from station.report.export import export_bytes

    return export_bytes(path, name)


@router.get("/{run_id}/archive.zip", response_class=Response, dependencies=[Reader],
            responses={200: {"description": "ZIP: the HDF5 recording, its stored results (<run>.results/), the "
                             "certificates issued for it (certificates/) and MANIFEST.json (SHA-256 and size of "
                             "each file)", "content": {"application/zip": {"schema": BINARY}}},
                       **NON_JSON_ERRORS},
            summary="The recording with its results and certificates as one archive")
async def run_archive(run: RunDep, artifacts: ArtifactsDep) -> Response:
    from station.recording.archive import recording_archive

    path = ended_recording(run, artifacts)
    data = await artifacts.read_file(run.id, recording_archive)
    return Response(data, media_type="application/zip",
                    headers={"Content-Disposition": f'attachment; filename="{path.stem}.zip"'})
