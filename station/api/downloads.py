"""File downloads in the OpenAPI document, declared so that generic clients read them as bytes.

A route that answers a file (PNG, PDF, HDF5, XLSX, CSV, the certificate's HTML/PDF/XML) declares its
media types with a binary schema.  Client generators understand few media types by name: without an
override, ``openapi-python-client`` leaves out an operation whose only content is ``image/png`` and
types one whose first is ``text/html`` as ``str`` even when it answers PDF.  Every such response
therefore also declares ``application/octet-stream`` (first): generators then read the answer as
bytes whatever its actual ``Content-Type``, which stays the specific one the route sends."""

from __future__ import annotations

from typing import Any

OCTET = "application/octet-stream"


def is_binary(media: dict[str, Any]) -> bool:
    schema = media.get("schema") or {}
    return schema.get("type") == "string" and schema.get("format") == "binary"


def declare_downloads(doc: dict[str, Any]) -> dict[str, Any]:
    """The OpenAPI document with ``application/octet-stream`` first in every successful response
    that has a binary media type."""
    for ops in doc.get("paths", {}).values():
        for op in ops.values():
            if not isinstance(op, dict):
                continue
            for code, resp in op.get("responses", {}).items():
                content = resp.get("content") or {}
                if not (code.startswith("2") and any(is_binary(m) for m in content.values())):
                    continue
                resp["content"] = {OCTET: {"schema": {"type": "string", "format": "binary"}},
                                   **{k: v for k, v in content.items() if k != OCTET}}
    return doc
