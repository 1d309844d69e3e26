"""Errors as RFC 9457 problem details (``application/problem+json``): one shape for every refusal
of every route, with a machine-readable ``type`` per kind of refusal.

``{"type": "urn:sinecal:problem:<kind>", "title": <the kind, in words>, "status": <HTTP status>,
"detail": <this occurrence, for the operator>, "instance": <the request's path>}``, and for invalid
input (422) ``errors``: the offending fields (``loc``, ``msg``, ``type``).  The OpenAPI document
declares every 4xx/5xx response so (:func:`declare_problems`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from fastapi import HTTPException
from fastapi.responses import JSONResponse

MEDIA_TYPE = "application/problem+json"
TYPE_PREFIX = "urn:sinecal:problem:"

# kind -> title (what the kind of refusal is, in words)
KINDS: dict[str, str] = {
    "bad-request": "The request could not be read",
    "not-logged-in": "Not logged in",
    "credentials-refused": "The login or token was not accepted",
    "forbidden": "Your role may not do this",
    "cross-site": "Refused: sent by another web site",
    "not-found": "Not found",
    "run-not-found": "No such run",
    "result-not-stored": "No such result stored",
    "certificate-not-found": "No such certificate",
    "entry-not-found": "No such entry in the register",
    "user-not-found": "No such user",
    "method-not-allowed": "Method not allowed",
    "run-state": "The run is not in a state that allows this",
    "rig-busy": "Another run holds the rig",
    "emergency-stop-latched": "The emergency stop is latched",
    "certificate-refused": "The certificate cannot be issued",
    "register-conflict": "The register refuses this change",
    "user-conflict": "The change of users is refused",
    "recording-tampered": "A recording was changed outside the station",
    "body-too-large": "The request body is too large",
    "unsupported-media-type": "The request body must be JSON",
    "invalid-input": "Invalid input",
    "compensation-refused": "No compensation filter can be made or applied for this input",
    "rig-unavailable": "The rig cannot be reached",
    "database-busy": "The station's database is busy",
    "unavailable": "Cannot be read or written right now",
    "internal-error": "Internal error of the station daemon",
}

NOT_LOGGED_IN = ("you are not logged in: log in at the top of the station's page (a script sends an API token "
                 "instead, in the header 'Authorization: Bearer <token>')")

BY_STATUS = {400: "bad-request", 401: "credentials-refused", 403: "forbidden", 404: "not-found",
             405: "method-not-allowed", 409: "run-state", 413: "body-too-large", 415: "unsupported-media-type",
             422: "invalid-input", 503: "unavailable", 500: "internal-error"}


def type_uri(kind: str) -> str:
    return TYPE_PREFIX + kind


def kind_of_status(status: int) -> str:
    return BY_STATUS.get(status, "bad-request" if status < 500 else "internal-error")


def problem(status: int, kind: str, detail: str, instance: str | None = None,
            errors: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """A problem document (``kind``: a key of :data:`KINDS`)."""
    doc: dict[str, Any] = {"type": type_uri(kind), "title": KINDS.get(kind, KINDS[kind_of_status(status)]),
                           "status": status, "detail": detail}
    if instance is not None:
        doc["instance"] = instance
    if errors is not None:
        doc["errors"] = errors
    return doc


def problem_response(status: int, kind: str, detail: str, instance: str | None = None,
                     errors: list[dict[str, Any]] | None = None,
                     headers: Mapping[str, str] | None = None) -> JSONResponse:
    return JSONResponse(problem(status, kind, detail, instance, errors), status_code=status,
                        headers=dict(headers or {}), media_type=MEDIA_TYPE)


def problem_bytes(status: int, kind: str, detail: str, instance: str | None = None,
                  errors: list[dict[str, Any]] | None = None) -> bytes:
    """The document as the body of a response sent below the framework (api/guard.py)."""
    return json.dumps(problem(status, kind, detail, instance, errors)).encode()


def errors_text(errors: list[dict[str, Any]]) -> str:
    """Invalid input in one sentence: ``field: message; ...`` (steps counted from 1 for people)."""
    parts = []
    for e in errors:
        loc = [x for x in e.get("loc", []) if x not in ("body", "query", "path")]
        where = ".".join(f"{x + 1}" if isinstance(x, int) else str(x) for x in loc)
        parts.append(f"{where}: {e.get('msg', '')}" if where else str(e.get("msg", "")))
    return "; ".join(parts) or "invalid input"


class Refusal(HTTPException):
    """An HTTP refusal of the API layer with its kind of problem (a key of :data:`KINDS`)."""

    def __init__(self, status: int, kind: str, detail: str, headers: dict[str, str] | None = None,
                 errors: list[dict[str, Any]] | None = None) -> None:
        super().__init__(status, detail, headers=headers)
        self.kind = kind
        self.errors = errors  # a 422's fields (loc, msg, type), as the validation problems list them


def declare_problems(doc: dict[str, Any]) -> dict[str, Any]:
    """The OpenAPI document with every 4xx/5xx response as ``application/problem+json`` (422: the
    ``ValidationProblem`` schema, others ``Problem``), and every operation declaring 500."""
    schemas = doc.setdefault("components", {}).setdefault("schemas", {})
    schemas.pop("HTTPValidationError", None)
    schemas.pop("ValidationError", None)
    for ops in doc.get("paths", {}).values():
        for op in ops.values():
            if not isinstance(op, dict) or "responses" not in op:
                continue
            responses = op["responses"]
            responses.setdefault("500", {"description": "internal error of the station daemon (its log has the "
                                                         "details)"})
            for code, resp in responses.items():
                if not (code.isdigit() and int(code) >= 400):
                    continue
                name = "ValidationProblem" if code == "422" else "Problem"
                resp["content"] = {MEDIA_TYPE: {"schema": {"$ref": f"#/components/schemas/{name}"}}}
                if code == "422" and resp.get("description") == "Validation Error":
                    resp["description"] = "invalid input; `errors` names each field"
    return doc
