"""What every request passes before any route sees it (pure ASGI, no body buffering by the framework):

* a request body is read only from an authenticated client: a POST/PUT/PATCH that carries a body
  without a valid bearer token or page session is answered 401 before a byte of it is read, except
  the login itself (whose body is the credential; bounded like any other); the emergency stop
  needs no token and reads no body; every other endpoint that takes a body computes or stores);
* a body that is not JSON by its ``Content-Type`` (form, multipart, text/plain, octet-stream, ...)
  is answered 415 unread: every body the API takes is JSON, and a browser can send the other types
  from any web site without asking;
* a body larger than ``service.max_body_bytes`` is answered 413, saying the limit, without being
  read further (by its Content-Length when given, else while it arrives);
* a JSON body that is not UTF-8 is answered 422 naming the first bad byte (never a 500).
"""

from __future__ import annotations

import secrets
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from station.api.problems import MEDIA_TYPE, errors_text, problem_bytes

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

OPEN_POSTS = ("/stop",)  # accepted without the token; their bodies are never read
LOGIN_POSTS = ("/login",)  # the body is the credential: read (bounded, JSON only) without one
QUOTE_CHARS = 120  # at most this much of a header value is quoted back


def is_json_type(ctype: bytes) -> bool:
    """``application/json`` or a ``+json`` type, parameters aside; no Content-Type counts as JSON."""
    media = ctype.split(b";", 1)[0].strip().lower()
    return not media or media == b"application/json" or (media.startswith(b"application/")
                                                         and media.endswith(b"+json"))


async def _answer(send: Send, status: int, kind: str, detail: str, path: str,
                  headers: list[tuple[bytes, bytes]] | None = None, errors: list[dict[str, Any]] | None = None) -> None:
    body = problem_bytes(status, kind, detail, path or None, errors)
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", MEDIA_TYPE.encode()), (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close"), *(headers or [])]})
    await send({"type": "http.response.body", "body": body})


Authenticate = Callable[[dict[bytes, bytes]], Awaitable[tuple[str, str] | None]]  # (kind, reason) or None


class BodyGuard:
    """``authenticate(headers)``: None for a request with valid credentials (a token or a page
    session), else the kind of problem and the reason it is refused; without it, only ``token`` is
    accepted."""

    def __init__(self, app: ASGIApp, *, token: str, max_body_bytes: int,
                 authenticate: Authenticate | None = None) -> None:
        self.app = app
        self._token = f"Bearer {token}".encode()
        self.max_body_bytes = max_body_bytes
        self._authenticate = authenticate

    async def _refusal(self, headers: dict[bytes, bytes]) -> tuple[str, str] | None:
        if self._authenticate is not None:
            return await self._authenticate(headers)
        auth = headers.get(b"authorization", b"")
        scheme, _, cred = auth.partition(b" ")
        ok = scheme.lower() == b"bearer" and secrets.compare_digest(b"Bearer " + cred.strip(), self._token)
        return None if ok else ("credentials-refused",
                                "a valid bearer token is required (Authorization: Bearer <token>)")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] not in ("POST", "PUT", "PATCH"):
            await self.app(scope, receive, send)
            return
        headers = {k.lower(): v for k, v in scope.get("headers", [])}
        length_text: bytes | None = headers.get(b"content-length")
        chunked = b"chunked" in headers.get(b"transfer-encoding", b"").lower()
        try:
            length = int(length_text) if length_text is not None else None
        except ValueError:
            await _answer(send, 400, "bad-request", f"Content-Length {(length_text or b'')[:QUOTE_CHARS]!r} is not a "
                          "number", scope.get("path", ""))
            return
        has_body = chunked or (length or 0) > 0
        path = scope.get("path", "")
        if path in OPEN_POSTS or not has_body:
            await self.app(scope, receive, send)  # the route's own dependencies decide (no body to read)
            return
        refusal = None if path in LOGIN_POSTS else await self._refusal(headers)
        if refusal is not None:
            await _answer(send, 401, refusal[0], f"{refusal[1]}; the request body was not read", path,
                          [(b"www-authenticate", b"Bearer")])
            return
        ctype = headers.get(b"content-type", b"")
        if not is_json_type(ctype):
            shown = ctype[:QUOTE_CHARS].decode("latin-1")
            await _answer(send, 415, "unsupported-media-type", "the request body must be JSON (Content-Type: "
                          f"application/json), got Content-Type {shown!r}; the body was not read", path)
            return
        limit = self.max_body_bytes
        if length is not None and length > limit:
            await _answer(send, 413, "body-too-large", f"request body of {length} bytes exceeds the limit of "
                          f"{limit} bytes (service.max_body_bytes)", path)
            return
        # read the (authorised, bounded) body here, check it, then hand it on in one piece
        chunks, size = [], 0
        while True:
            msg = await receive()
            if msg["type"] == "http.disconnect":
                return
            part = msg.get("body", b"")
            size += len(part)
            if size > limit:
                await _answer(send, 413, "body-too-large", f"request body exceeds the limit of {limit} bytes "
                              "(service.max_body_bytes)", path)
                return
            chunks.append(part)
            if not msg.get("more_body", False):
                break
        body = b"".join(chunks)
        try:
            body.decode("utf-8")
        except UnicodeDecodeError as exc:
            errors: list[dict[str, Any]] = [
                {"type": "body_not_utf8", "loc": ["body"], "input": None,
                 "msg": f"the request body must be UTF-8 encoded JSON; byte 0x{body[exc.start]:02x} at position "
                        f"{exc.start} is not UTF-8"}]
            await _answer(send, 422, "invalid-input", errors_text(errors), path, errors=errors)
            return
        sent = False

        async def replay() -> Message:
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)
