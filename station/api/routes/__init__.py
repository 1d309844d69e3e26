"""The API's routers: each module's ``router`` is made by :func:`api_router`, its routes built once
as the module is imported and added to every app as they are (``station.api.main.add_routes``)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from fastapi.routing import APIRoute


def operation_id(route: APIRoute) -> str:
    """An operation's id in the OpenAPI document: its function's name (``start_run``), so that
    generated clients get readable names."""
    return route.name


def api_router(**kw: Any) -> APIRouter:
    """An ``APIRouter`` (``kw``: its prefix and tags) whose routes carry the API's operation ids."""
    return APIRouter(generate_unique_id_function=operation_id, **kw)
