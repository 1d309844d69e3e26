"""Typed dependencies: settings, the run manager, who makes the request and what they may do, a run
looked up by id.

Who: a bearer token (the configured ``STATION_TOKEN``/``service.token`` acts for the administrator
``admin``; tokens issued to users act for them) or the page's session cookie (HttpOnly, expiring).
Looking either up reads the database through the read pool (never on the event loop).

All are ``async def``: they are cheap, and FastAPI would run plain functions in its thread pool
(a thread hop per dependency and request, which shows in the status latency under load)."""

from __future__ import annotations

import secrets
from collections.abc import Awaitable, Callable
from typing import Annotated

from fastapi import Depends, Path, Request, Security, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from station.api.problems import NOT_LOGGED_IN, Refusal
from station.lab import users
from station.lab.store import RunRow, Store
from station.lab.users import AuthError, Permission, Principal, Role, User
from station.service.artifacts import Artifacts
from station.service.manager import TOKEN_USER, RunManager, RunNotFoundError
from station.service.runs import Runs
from station.service.settings import ServiceSettings, is_loopback

bearer = HTTPBearer(auto_error=False, description="an API token: the station's (service.token or STATION_TOKEN, "
                    "acting for the administrator 'admin') or one issued to a user (POST /users/{name}/tokens)")

RUN_ID_PATTERN = r"^[A-Za-z0-9_.\-]{1,128}$"
SESSION_COOKIE = "station_session"


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


def station_token(token: str, settings: ServiceSettings) -> Principal | None:
    """The configured token's principal (the administrator ``admin``), without the database."""
    if secrets.compare_digest(token.encode(), settings.token.encode()):
        return Principal(User(TOKEN_USER, Role.ADMIN), "token")
    return None


def token_lookup(token: str, settings: ServiceSettings) -> Callable[[Store], Principal | None]:
    """A function of the store giving the token's user (None: not a token of this station)."""
    def find(store: Store) -> Principal | None:
        if (who := station_token(token, settings)) is not None:
            return who
        user = users.user_of_token(store, token)
        return None if user is None or user.disabled else Principal(user, "token")
    return find


def credentials_of(headers: dict[str, str]) -> tuple[str | None, str | None]:
    """(bearer token, session cookie) of a request's headers (lower-case names)."""
    auth = headers.get("authorization", "")
    scheme, _, cred = auth.partition(" ")
    token = cred.strip() if scheme.lower() == "bearer" and cred.strip() else None
    session = None
    for part in headers.get("cookie", "").split(";"):
        k, _, v = part.strip().partition("=")
        if k == SESSION_COOKIE and v:
            session = v
    return token, session


async def authenticate(manager: RunManager | None, settings: ServiceSettings, token: str | None,
                       session: str | None) -> Principal | None:
    """Who the credentials belong to; None without credentials; AuthError (with the reason) for
    credentials that are wrong, ended or expired."""
    if token is not None and (who := station_token(token, settings)) is not None:
        return who
    if manager is None and (token or session):
        raise AuthError("the station daemon is starting; try again")
    if token is not None:
        assert manager is not None
        who = await manager.db.read(token_lookup(token, settings))
        if who is None:
            raise AuthError("the bearer token is not valid for this station (check STATION_TOKEN or ask an "
                            "administrator for a token)")
        return who
    if session is not None:
        assert manager is not None
        return await manager.db.read(lambda store: users.session_user(store, session))
    return None


async def principal(request: Request, creds: Credentials, settings: SettingsDep) -> Principal | None:
    _, session = credentials_of({"cookie": request.headers.get("cookie", "")})
    try:
        who = await authenticate(getattr(request.app.state, "manager", None), settings,
                                 creds.credentials if creds else None, session)
    except AuthError as exc:
        raise Refusal(status.HTTP_401_UNAUTHORIZED, "credentials-refused", str(exc),
                      headers={"WWW-Authenticate": "Bearer"}) from None
    return who


PrincipalDep = Annotated[Principal | None, Depends(principal)]


def _same_site(request: Request) -> None:
    """A page session's change must come from the station's own page (the cookie is SameSite=Strict
    too): the browser's Sec-Fetch-Site and Origin say where a request comes from."""
    site = request.headers.get("sec-fetch-site")
    origin = request.headers.get("origin")
    if (site is not None and site not in ("same-origin", "none")) or \
            (origin is not None and origin.split("://", 1)[-1] != request.headers.get("host", "")):
        raise Refusal(status.HTTP_403_FORBIDDEN, "cross-site", "cross-site request refused; use the station's own page")


def require(perm: Permission) -> Callable[..., Awaitable[Principal]]:
    """A dependency: the request's user, who must hold ``perm`` (401 without credentials, 403 with
    a role that does not grant it)."""
    async def check(request: Request, who: PrincipalDep) -> Principal:
        if who is None:
            raise Refusal(status.HTTP_401_UNAUTHORIZED, "not-logged-in", NOT_LOGGED_IN,
                          headers={"WWW-Authenticate": "Bearer"})
        if not who.user.may(perm):
            roles = ", ".join(str(r) for r, g in users.GRANTS.items() if perm in g)
            raise Refusal(status.HTTP_403_FORBIDDEN, "forbidden", f"user {who.name} ({who.user.role}) may not do "
                          f"this: it needs the '{perm}' permission ({roles})")
        if who.via == "session":
            _same_site(request)
        return who
    return check


async def read_access(request: Request, who: PrincipalDep) -> None:
    """Reading is open to clients on loopback; others need a token or a page session."""
    client = request.client.host if request.client else ""
    if is_loopback(client) or who is not None:
        return
    raise Refusal(status.HTTP_401_UNAUTHORIZED, "not-logged-in", "reading from outside this machine needs a "
                  "login or an API token", headers={"WWW-Authenticate": "Bearer"})


RunId = Annotated[str, Path(pattern=RUN_ID_PATTERN, description="run id as returned by POST /runs")]


async def get_run(run_id: RunId, runs: RunsDep) -> RunRow:
    try:
        return await runs.get(run_id)
    except RunNotFoundError as exc:
        raise Refusal(status.HTTP_404_NOT_FOUND, "run-not-found", str(exc)) from None


RunDep = Annotated[RunRow, Depends(get_run)]
require_token = require(Permission.RUN)  # the name older routes use
Writer = Depends(require_token)
Reader = Depends(read_access)
Operator = Annotated[Principal, Depends(require_token)]
Approver = Annotated[Principal, Depends(require(Permission.APPROVE))]
Admin = Annotated[Principal, Depends(require(Permission.ADMIN))]
