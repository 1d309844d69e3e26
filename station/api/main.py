"""The FastAPI application: ``create_app(settings)``.

The app owns one RunManager (rig connection, runs, job queue) for its lifetime: started in the
lifespan, closed on shutdown (a run on the rig is stopped first).  Service errors are mapped to
HTTP statuses here; nothing below the API layer knows about HTTP.
"""

from __future__ import annotations

import copy
import json
import logging
import sqlite3
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.routing import APIRouter
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.middleware.trustedhost import TrustedHostMiddleware

from station import __version__
from station.api.deps import authenticate, credentials_of
from station.api.downloads import declare_downloads
from station.api.guard import BodyGuard
from station.api.problems import NOT_LOGGED_IN, Refusal, declare_problems, errors_text, kind_of_status, problem_response
from station.api.routes import (
    campaign,
    certificates,
    compensation,
    exports,
    lab,
    operation_id,
    proposal,
    runs,
    system,
)
from station.errors import StationError
from station.lab.integrity import RecordingTamperedError
from station.lab.issued import CertificateError, CertificateNotFoundError
from station.lab.register import RegisterError, UnknownEntryError
from station.lab.users import AuthError, ForbiddenError, UnknownUserError, UserError
from station.service.errors import DatabaseBusyError, ResultNotStoredError
from station.service.manager import (
    EStopLatchedError,
    RigBusyError,
    RigUnavailableError,
    RunManager,
    RunNotFoundError,
    RunStateError,
)
from station.service.results import finite
from station.service.settings import ServiceSettings

log = logging.getLogger(__name__)

STATIC = Path(__file__).resolve().parent / "static"

DESCRIPTION = """Calibration-station daemon: start stepped-sine calibration runs on the sine-mechanism
rig, follow them live, read the identified transducer parameters, plots, report and recording.

Endpoints that move the rig, change state or compute and store (`POST /runs`, `POST /runs/{id}/abort`,
`POST /stop/acknowledge`, `POST /runs/{id}/discrepancy`) need the bearer token (`service.token` or
`STATION_TOKEN`); reading is open on loopback and never writes; `POST /stop` (emergency stop) is
always accepted, except from another web site.  After an emergency stop no run starts until an
operator acknowledges it.  Units are SI and part of every field name."""


QUOTE_CHARS = 200  # the most of a request's input a validation error quotes back


def _quoted(value: Any) -> Any:
    """A request's input as a validation error quotes it: JSON as it came, or, when that is long or
    not JSON at all, at most ``QUOTE_CHARS`` characters of its text."""
    if isinstance(value, str):
        return value if len(value) <= QUOTE_CHARS else f"{value[:QUOTE_CHARS]}... ({len(value)} characters)"
    try:
        text = json.dumps(finite(jsonable_encoder(value)), allow_nan=False)
    except (TypeError, ValueError):  # bytes that are not UTF-8, objects JSON has no form for
        text = repr(value)
    else:
        if len(text) <= QUOTE_CHARS:
            return finite(jsonable_encoder(value))
    if len(text) <= QUOTE_CHARS:
        return text
    return f"{text[:QUOTE_CHARS]}... ({len(text)} characters)"


def validation_details(errors: Sequence[Any]) -> list[dict[str, Any]]:
    """FastAPI's error list, made safe to send: every ``input`` quoted within ``QUOTE_CHARS``,
    messages and contexts as text of bounded length."""
    out = []
    for err in errors:
        e = dict(err)
        if "input" in e:
            e["input"] = _quoted(e["input"])
        if "ctx" in e:
            e["ctx"] = {str(k): _quoted(v) for k, v in dict(e["ctx"]).items()}
        e["msg"] = str(e.get("msg", ""))[:4 * QUOTE_CHARS]
        e.pop("url", None)
        out.append(e)
    return out


# The OpenAPI documents made in this process, by what they are made of: an app's title, version and
# description and the very route objects it documents (shared by the apps of a process: add_routes),
# kept with the document so that their ids stay theirs.
_DOCUMENTS: dict[tuple[Any, ...], tuple[tuple[Any, ...], dict[str, Any]]] = {}


def openapi_document(app: FastAPI) -> dict[str, Any]:
    """The app's OpenAPI document (problem details and downloads declared), made once per process
    for the same routes: FastAPI builds a field of every model's every field to find the models
    (some 0.6 s of CPU), and the apps of a process document the same route objects.  Read only."""
    documented = tuple(r for r in app.routes if getattr(r, "include_in_schema", False))
    key = (app.title, app.version, app.openapi_version, app.description, tuple(id(r) for r in documented))
    if key not in _DOCUMENTS:
        _DOCUMENTS[key] = documented, declare_downloads(declare_problems(get_openapi(
            title=app.title, version=app.version, openapi_version=app.openapi_version,
            description=app.description, routes=app.routes)))
    return _DOCUMENTS[key][1]


def install_error_handlers(app: FastAPI) -> None:
    """Every refusal as RFC 9457 problem details (station/api/problems.py), with its kind."""
    kinds: list[tuple[type[Exception], int, str]] = [
        (RunNotFoundError, 404, "run-not-found"), (ResultNotStoredError, 404, "result-not-stored"),
        (RunStateError, 409, "run-state"), (RigBusyError, 409, "rig-busy"),
        (EStopLatchedError, 409, "emergency-stop-latched"), (RigUnavailableError, 503, "rig-unavailable"),
        (DatabaseBusyError, 503, "database-busy"), (CertificateNotFoundError, 404, "certificate-not-found"),
        (CertificateError, 409, "certificate-refused"), (AuthError, 401, "credentials-refused"),
        (ForbiddenError, 403, "forbidden"), (UnknownEntryError, 404, "entry-not-found"),
        (RegisterError, 409, "register-conflict"), (UnknownUserError, 404, "user-not-found"),
        (UserError, 409, "user-conflict"), (RecordingTamperedError, 409, "recording-tampered")]
    for cls, code, kind in kinds:
        def handler(request: Request, exc: Exception, code: int = code, kind: str = kind) -> JSONResponse:
            return problem_response(code, kind, str(exc), request.url.path)
        app.add_exception_handler(cls, handler)

    async def validation_error(request: Request, exc: Exception) -> JSONResponse:
        # FastAPI's own handler echoes the input, which cannot be JSON when it is NaN or inf (-> 500)
        errors = validation_details(exc.errors() if isinstance(exc, RequestValidationError) else [])
        return problem_response(422, "invalid-input", errors_text(errors), request.url.path, errors)
    app.add_exception_handler(RequestValidationError, validation_error)

    async def http_error(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, StarletteHTTPException)
        if exc.status_code == 400 and request.method in ("POST", "PUT", "PATCH"):
            # a body that is not even text (FastAPI says 400): bad input like any other, 422
            errors = [{"type": "body_unreadable", "loc": ["body"], "msg": str(exc.detail)}]
            return problem_response(422, "invalid-input", errors_text(errors), request.url.path, errors)
        if exc.status_code < 400:
            return Response(status_code=exc.status_code, headers=exc.headers)
        kind = exc.kind if isinstance(exc, Refusal) else kind_of_status(exc.status_code)
        fields = exc.errors if isinstance(exc, Refusal) else None
        return problem_response(exc.status_code, kind, str(exc.detail), request.url.path, fields, headers=exc.headers)
    app.add_exception_handler(StarletteHTTPException, http_error)

    async def station_error(request: Request, exc: Exception) -> JSONResponse:
        # a recording that cannot be read or written right now (locked by another process, damaged)
        log.warning("%s %s: %s", request.method, request.url.path, exc)
        return problem_response(503, "unavailable", str(exc), request.url.path)
    app.add_exception_handler(StationError, station_error)
    app.add_exception_handler(OSError, station_error)
    app.add_exception_handler(sqlite3.Error, station_error)  # e.g. the database's disk is full

    async def internal_error(request: Request, exc: Exception) -> JSONResponse:
        # a bug: the traceback goes to the daemon's log, never to the client
        log.error("%s %s: internal error", request.method, request.url.path, exc_info=exc)
        return problem_response(500, "internal-error", "internal error of the station daemon; the details are "
                                "in its log", request.url.path)
    app.add_exception_handler(Exception, internal_error)

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = copy.deepcopy(openapi_document(app))  # the app's own, to change if it will
        return app.openapi_schema
    app.openapi = openapi  # type: ignore[method-assign]


class StartupFailureLine:
    """A daemon that cannot start says why in one line: the framework reports a failed start-up with
    the whole traceback, which goes to the debug log; the error line is its last line (the
    exception and its message)."""

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "lifespan":
            await self.app(scope, receive, send)
            return

        async def one_line(message: Any) -> None:
            if message.get("type") == "lifespan.startup.failed" and message.get("message"):
                text = str(message["message"]).strip()
                log.debug("start-up failed:\n%s", text)
                last = text.splitlines()[-1] if text else "unknown error"
                message = {**message, "message": f"the station daemon cannot start: {last} (details: -v)"}
            await send(message)
        await self.app(scope, receive, one_line)


def add_routes(app: FastAPI, *routers: APIRouter) -> None:
    """The routers' routes added to ``app`` as they are: built once, as their modules were imported,
    and shared by every app of the process.  (``include_router`` would have each app build every
    route again, with their models' fields and dependencies, on its first request: some 0.15 s of
    CPU per app.)  The routers carry the API's prefixes, tags and operation ids themselves
    (``station.api.routes.api_router``); the app adds nothing to them."""
    for router in routers:
        app.router.routes.extend(router.routes)


def install_docs(app: FastAPI) -> None:
    """Swagger UI at /docs and ReDoc at /redoc, their assets served from the ``fastapi-offline``
    package (Swagger UI 5, which reads OpenAPI 3.1) under /docs-assets."""
    import fastapi_offline
    from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html

    assets = Path(fastapi_offline.__file__).resolve().parent / "static"
    app.mount("/docs-assets", StaticFiles(directory=assets), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    async def swagger() -> Response:
        return get_swagger_ui_html(openapi_url="/openapi.json", title="sinecal station: API",
                                   swagger_js_url="/docs-assets/swagger-ui-bundle.js",
                                   swagger_css_url="/docs-assets/swagger-ui.css",
                                   swagger_favicon_url="/docs-assets/favicon.png")

    @app.get("/redoc", include_in_schema=False)
    async def redoc() -> Response:
        return get_redoc_html(openapi_url="/openapi.json", title="sinecal station: API",
                              redoc_js_url="/docs-assets/redoc.standalone.js",
                              redoc_favicon_url="/docs-assets/favicon.png", with_google_fonts=False)


def create_app(settings: ServiceSettings, *,
               manager_factory: Callable[[ServiceSettings], RunManager] | None = None) -> FastAPI:
    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        manager = (manager_factory or RunManager)(settings)
        app.state.manager = manager
        await manager.start()
        try:
            yield
        finally:
            await manager.close()

    # the API's pages (/docs, /redoc) load their scripts from this daemon, never from a CDN: a lab
    # network is often isolated (install_docs)
    app = FastAPI(title="sinecal station", version=__version__, description=DESCRIPTION, lifespan=lifespan,
                  generate_unique_id_function=operation_id, docs_url=None, redoc_url=None)
    app.state.settings = settings
    if settings.loopback_only:  # refuse other Host headers (DNS rebinding against the open reads)
        app.add_middleware(TrustedHostMiddleware,
                           allowed_hosts=["127.0.0.1", "localhost", "::1", "[::1]"])
    install_error_handlers(app)
    # outermost: authenticate and bound a request body before anything reads it
    async def body_refusal(headers: dict[bytes, bytes]) -> tuple[str, str] | None:
        manager = getattr(app.state, "manager", None)
        if manager is None:
            return "credentials-refused", "the station daemon is starting"
        token, session = credentials_of({k.decode("latin-1"): v.decode("latin-1") for k, v in headers.items()})
        if token is None and session is None:
            return "not-logged-in", NOT_LOGGED_IN
        try:
            return None if await authenticate(manager, settings, token, session) else ("not-logged-in", NOT_LOGGED_IN)
        except AuthError as exc:
            return "credentials-refused", str(exc)
    app.add_middleware(BodyGuard, token=settings.token, max_body_bytes=settings.config.service.max_body_bytes,
                       authenticate=body_refusal)
    app.add_middleware(StartupFailureLine)
    add_routes(app, runs.router, exports.router, certificates.router, campaign.router, proposal.router,
               system.router, lab.router, compensation.router)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    install_docs(app)

    @app.get("/", include_in_schema=False)
    async def index() -> FileResponse:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})

    return app
