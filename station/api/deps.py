"""Typed dependencies: settings, the run manager and the services it holds (runs, artifacts),
authorisation, a run looked up by id.

All are ``async def``: they are cheap, and FastAPI would run plain functions in its thread pool
(a thread hop per dependency and request, which shows in the status latency under load)."""

from __future__ import annotations

import secrets
from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request, Security, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from station.service.artifacts import Artifacts
from station.service.manager import RunManager, RunNotFoundError
from station.service.runs import Runs
from station.service.settings import ServiceSettings, is_loopback
from station.service.store import RunRow

bearer = HTTPBearer(auto_error=False, description="the station token (service.token or STATION_TOKEN)")

RUN_ID_PATTERN = r"^[A-Za-z0-9_.\-]{1,128}$"


async def get_settings(request: Request) -> ServiceSettings:
    return request.app.state.settings


async def get_manager(request: Request) -> RunManager:
    return request.app.state.manager


SettingsDep = Annotated[ServiceSettings, Depends(get_settings)]
ManagerDep = Annotated[RunManager, Depends(get_manager)]


async def get_runs(manager: ManagerDep) -> Runs:
    return manager.runs


async def get_artifacts(manager: ManagerDep) -> Artifacts:
    return manager.artifacts


RunsDep = Annotated[Runs, Depends(get_runs)]  # the runs on the rig and the stored ones
ArtifactsDep = Annotated[Artifacts, Depends(get_artifacts)]  # recordings and what is rendered from them
Credentials = Annotated[HTTPAuthorizationCredentials | None, Security(bearer)]


def _token_ok(creds: HTTPAuthorizationCredentials | None, settings: ServiceSettings) -> bool:
    return creds is not None and secrets.compare_digest(creds.credentials.encode(), settings.token.encode())


async def require_token(creds: Credentials, settings: SettingsDep) -> None:
    """Endpoints that move the rig or change state: the bearer token, always."""
    if not _token_ok(creds, settings):
        raise HTTPException(status.HTTP_401_UNAUTHORIZED,
                            "a valid bearer token is required (Authorization: Bearer <token>)",
                            headers={"WWW-Authenticate": "Bearer"})


async def read_access(request: Request, creds: Credentials, settings: SettingsDep) -> None:
    """Reading is open to clients on loopback; others need the token."""
    client = request.client.host if request.client else ""
    if is_loopback(client) or _token_ok(creds, settings):
        return
    raise HTTPException(status.HTTP_401_UNAUTHORIZED, "reading from outside this machine needs the bearer token",
                        headers={"WWW-Authenticate": "Bearer"})


RunId = Annotated[str, Path(pattern=RUN_ID_PATTERN, description="run id as returned by POST /runs")]


async def get_run(run_id: RunId, runs: RunsDep) -> RunRow:
    try:
        return await runs.get(run_id)
    except RunNotFoundError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None


RunDep = Annotated[RunRow, Depends(get_run)]
Writer = Depends(require_token)
Reader = Depends(read_access)
