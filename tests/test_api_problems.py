"""Refusals as RFC 9457 problem details: the OpenAPI document declares every 4xx/5xx response of
every operation as ``application/problem+json``, and refusals of every kind (the body guard's, the
dependencies', the service's, validation, unknown paths) come in that one shape with their kind."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import httpx
import pytest

from station.api.problems import KINDS, MEDIA_TYPE, TYPE_PREFIX
from station.api.schemas import Problem, ValidationProblem
from tests.station_support import CAPPED_SPEEDUP, app_in_process, asgi_client, run_body


def _responses(doc: dict[str, Any]) -> list[tuple[str, str, str, dict[str, Any]]]:
    return [(path, method, code, resp) for path, ops in doc["paths"].items() for method, op in ops.items()
            for code, resp in op["responses"].items()]


def _check(r: httpx.Response, status: int, kind: str) -> dict[str, Any]:
    assert r.status_code == status, (r.status_code, r.text)
    assert r.headers["content-type"] == MEDIA_TYPE, (r.headers["content-type"], r.text)
    body = r.json()
    (ValidationProblem if status == 422 else Problem).model_validate(body)  # the declared schema, exactly
    assert body["type"] == TYPE_PREFIX + kind and body["title"] == KINDS[kind] and body["status"] == status, body
    assert body["detail"] and "Traceback" not in r.text
    return body


@pytest.mark.slow
def test_every_error_response_of_the_openapi_document_is_problem_details(tmp_path: Path) -> None:
    async def go() -> dict[str, Any]:
        async with app_in_process(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP) as (_, c):
            return (await c.get("/openapi.json")).json()
    doc = asyncio.run(go())
    errors = [(p, m, code, resp) for p, m, code, resp in _responses(doc) if code.isdigit() and int(code) >= 400]
    assert len(errors) > 100  # every operation: at least its 500
    for path, method, code, resp in errors:
        name = "ValidationProblem" if code == "422" else "Problem"
        assert resp["content"] == {MEDIA_TYPE: {"schema": {"$ref": f"#/components/schemas/{name}"}}}, \
            (method, path, code, resp)
    for path, ops in doc["paths"].items():
        for method, op in ops.items():
            assert "500" in op["responses"], (method, path)
    schemas = doc["components"]["schemas"]
    assert {"type", "title", "status", "detail"} <= set(schemas["Problem"]["required"])
    assert "errors" in schemas["ValidationProblem"]["required"]
    assert "HTTPValidationError" not in schemas  # FastAPI's own shape is gone


def test_refusals_of_every_kind_come_as_problem_details(tmp_path: Path) -> None:
    async def go() -> None:
        async with app_in_process(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP) as (manager, c):
            app = c._transport.app  # type: ignore[attr-defined]
            async with asgi_client(app, token=False) as anon:
                # logged out: the body guard (with a body) and the dependency (without) say the same
                b = _check(await anon.post("/runs", json=run_body()), 401, "not-logged-in")
                assert "log in at the top of the station's page" in b["detail"] and b["instance"] == "/runs"
                _check(await anon.post("/runs"), 401, "not-logged-in")
                _check(await anon.get("/runs", headers={"Authorization": "Bearer wrong-token-123"}),
                       401, "credentials-refused")
            _check(await c.get("/runs/no-such-run"), 404, "run-not-found")
            _check(await c.get("/no-such-page"), 404, "not-found")
            _check(await c.get("/certificates/SC-0000-00000.pdf"), 404, "certificate-not-found")
            b = _check(await c.get("/runs?limit=0"), 422, "invalid-input")
            assert b["errors"][0]["loc"] == ["query", "limit"] and b["detail"].startswith("limit: ")
            b = _check(await c.post("/runs", json={**run_body(), "top_mass_kg": -1}), 422, "invalid-input")
            assert b["errors"][0]["loc"] == ["body", "top_mass_kg"]
            _check(await c.post("/runs", content=b"\xff\xfe", headers={"Content-Type": "application/json"}),
                   422, "invalid-input")
            _check(await c.post("/runs", content=b"a=1", headers={"Content-Type": "text/plain"}),
                   415, "unsupported-media-type")
            _check(await c.post("/runs", content=b"x" * (manager.settings.config.service.max_body_bytes + 1),
                                headers={"Content-Type": "application/json"}), 413, "body-too-large")
            _check(await c.delete("/runs"), 405, "method-not-allowed")
            r = await c.post("/runs", json=run_body())
            assert r.status_code == 202, r.text
            _check(await c.get(f"/runs/{r.json()['id']}/results"), 409, "run-state")
            _check(await c.post("/stop", headers={"Sec-Fetch-Site": "cross-site"}), 403, "cross-site")
    asyncio.run(go())
