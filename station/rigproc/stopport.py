"""The stop port: a listening socket of its own for the emergency stop (the rig process's; in the
daemon's own process: ``commands/stopport.py``).

The web side's port can be crowded (thousands of idle connections queue in the kernel's accept
backlog and each costs its loop time to accept and to close); a stop sent there waits behind them.
This listener shares nothing with the web side: its own socket (``service.stop_port``), its own
thread and event loop, a small HTTP/1.1 reader of its own, its own connection cap, and no
database.  It answers:

* ``POST /stop``: the stop of the :class:`Stops` it serves, with the main port's answer
  (:class:`station.api.schemas.StopOut`) and its cross-site rule, where the station's own page on
  the main port counts as this station.  In the rig process (``station/rigproc``) that is the
  emergency stop on the drive and its read-back, given there; in the daemon's own process
  (``commands/stopport.ManagerStops``) the very same stop as the main port's ``POST /stop``
  (:meth:`station.service.runs.Runs.emergency_stop`);
* ``GET /stop``: what is known without asking anyone (the latch, the drive's last reading).

Both only with a ``Host`` header that names this station (:func:`host_refusal`: a loopback name,
an IP address or a configured name), so that a page of another site cannot reach it through DNS
rebinding.

Bounds: a request head of at most :data:`MAX_HEAD_BYTES` within ``header_timeout_s`` of opening;
the body, if any, is never read (the stop takes none); every answer closes its connection; beyond
``max_connections`` open connections the oldest one still sending its head is closed for each new
one, so a stop always gets in.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import ipaddress
import json
import logging
import socket
import threading
from typing import TYPE_CHECKING, Any, Protocol
from urllib.parse import parse_qs, urlsplit

from station.service.priority import Priority, raise_priority
from station.service.rigthread import close_loop

if TYPE_CHECKING:
    from station.service.settings import ServiceSettings

log = logging.getLogger("station.stopport")

MAX_HEAD_BYTES = 8192  # request line and headers
MAX_HEADERS = 64
MAX_CONNECTIONS = 32
REASONS = {200: "OK", 400: "Bad Request", 403: "Forbidden", 404: "Not Found", 405: "Method Not Allowed",
           408: "Request Timeout", 431: "Request Header Fields Too Large", 500: "Internal Server Error"}


PROBLEM_KINDS = {400: "bad-request", 403: "cross-site", 404: "not-found", 405: "method-not-allowed",
                 408: "bad-request", 413: "body-too-large", 431: "bad-request", 500: "internal-error"}


class BadRequest(Exception):
    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail


def parse_head(head: bytes) -> tuple[str, str, dict[str, str]]:
    """(method, target, headers with lower-case names) of a request head (ending in a blank line);
    :class:`BadRequest` for anything that is not HTTP/1.x."""
    try:
        text = head.decode("latin-1")
    except UnicodeDecodeError:  # pragma: no cover - latin-1 decodes every byte
        raise BadRequest(400, "the request head is not text") from None
    lines = text.split("\r\n")
    parts = lines[0].split(" ")
    if len(parts) != 3 or not parts[2].startswith("HTTP/1.") or not parts[0].isalpha():
        raise BadRequest(400, f"not an HTTP/1.x request line: {lines[0][:80]!r}")
    headers: dict[str, str] = {}
    for line in lines[1:]:
        if not line:
            continue
        name, sep, value = line.partition(":")
        if not sep or not name or name != name.strip() or len(headers) >= MAX_HEADERS:
            raise BadRequest(400, f"malformed header line: {line[:80]!r}")
        key = name.lower()
        if key in headers and key in ("host", "origin", "content-length"):
            raise BadRequest(400, f"header {name} given twice")
        headers[key] = value.strip()
    if "transfer-encoding" in headers:
        raise BadRequest(400, "the stop takes no body (Transfer-Encoding refused)")
    length = headers.get("content-length", "0")
    if not length.isdigit():
        raise BadRequest(400, f"Content-Length {length[:40]!r} is not a number")
    return parts[0], parts[1], headers


def cross_site_refusal(site: str | None, origin: str | None, host: str,
                       page_origins: tuple[str, ...] = ()) -> str | None:
    """Why a request another web site's page made the browser send is refused (None: it is not
    one): browsers mark it with ``Sec-Fetch-Site: cross-site``/``same-site`` and an ``Origin`` that
    is not this station's (``host``, or one of ``page_origins``: ``host:port`` of the station's own
    page when it is served on another port).  API clients and curl (neither header) pass."""
    own = origin is not None and origin.split("://", 1)[-1] in (host, *page_origins)
    if site is not None and site not in ("same-origin", "none") and not (site == "same-site" and own):
        return (f"cross-site request refused (Sec-Fetch-Site: {site}); use the station's own page, an API client "
                "or the hardware emergency stop")
    if origin is not None and not own:
        return f"cross-site request refused: Origin {origin} is not this station ({host})"
    return None


def host_refusal(host: str, names: frozenset[str]) -> str | None:
    """Why a request whose ``Host`` header is ``host`` is refused (None: it names this station).

    A page of another site can reach a listener on this computer under a name of its own that it
    makes resolve to 127.0.0.1 (DNS rebinding); the browser then sends that name as ``Host``, and the
    request is same-origin to it.  So only names that cannot be such a page's are taken: a loopback
    name (``localhost``), an IP address (a page's origin is then that address itself), or one of
    ``names`` (lower case: the station's configured names)."""
    if not host:
        return "no Host header (HTTP/1.1 needs one)"
    if host.startswith("["):  # an IPv6 address, with or without a port
        end = host.find("]")
        rest = host[end + 1:] if end > 0 else "?"
        if end > 0 and (not rest or (rest.startswith(":") and rest[1:].isdigit())):
            with contextlib.suppress(ValueError):
                ipaddress.IPv6Address(host[1:end])
                return None
        return f"Host {host[:80]!r} is not a valid address"
    name, sep, port = host.rpartition(":")
    if not sep or not port.isdigit():
        name = host
    name = name.lower().rstrip(".")
    if name == "localhost" or name in names:
        return None
    with contextlib.suppress(ValueError):
        ipaddress.IPv4Address(name)
        return None
    return (f"Host {host[:80]!r} is not a name of this station (loopback names, IP addresses and "
            "service.host_names only); use the station's own page or its address")


def station_names(settings: ServiceSettings) -> frozenset[str]:
    """The names the stop port takes in a ``Host`` header besides loopback names and IP addresses:
    ``service.host_names`` and the listen address when it is a name."""
    names = {n.lower().rstrip(".") for n in settings.config.service.host_names}
    try:
        ipaddress.ip_address(settings.host)
    except ValueError:
        names.add(settings.host.lower().rstrip("."))
    return frozenset(names)


class Stops(Protocol):
    """What the stop port serves: ``state`` (``estop``: the latch, ``drive``: the last read-back;
    from memory, at once) and ``stop`` (the stop given; the answer in the shape of ``StopOut``)."""

    def state(self) -> dict[str, Any]: ...

    async def stop(self, source: str, headers: dict[str, str]) -> dict[str, Any]: ...


class StopPort:
    """The stop port's listener; ``start()`` binds and serves on a thread of its own, ``close()``.
    ``names``: taken in a ``Host`` header besides loopback names and addresses (:func:`station_names`)."""

    def __init__(self, stops: Stops, names: frozenset[str], host: str, port: int, *,
                 page_port: int | None = None, header_timeout_s: float = 5.0,
                 max_connections: int = MAX_CONNECTIONS, priority: Priority = "normal") -> None:
        self.stops = stops
        self.host = host
        self.port = port  # the bound port once started
        self.page_port = page_port  # the main port: the station's own page comes from there
        self.header_timeout_s = header_timeout_s
        self.max_connections = max_connections
        self.priority = priority  # the scheduling priority its thread asks for
        self.names = names
        self.loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server: asyncio.Server | None = None
        self._reading: collections.OrderedDict[int, asyncio.StreamWriter] = collections.OrderedDict()
        self._open = 0
        self.evicted = 0

    # ------------------------------------------------------------------ lifetime
    def start(self) -> StopPort:
        """Bind (OSError if the port is taken) and serve on the ``stop-port`` thread."""
        sock = socket.create_server((self.host, self.port), family=socket.AF_INET6 if ":" in self.host
                                    else socket.AF_INET, backlog=64, reuse_port=False)
        self.port = int(sock.getsockname()[1])
        ready = threading.Event()
        failure: list[BaseException] = []

        def main() -> None:
            if self.priority != "normal":
                raise_priority("stop-port", self.priority)
            loop = asyncio.new_event_loop()
            self.loop = loop
            try:
                self._server = loop.run_until_complete(
                    asyncio.start_server(self._serve, sock=sock, limit=MAX_HEAD_BYTES))
            except BaseException as exc:  # pragma: no cover - start_server on a bound socket
                failure.append(exc)
                ready.set()
                loop.close()
                return
            ready.set()
            try:
                loop.run_forever()
            finally:
                self._server.close()
                close_loop(loop)

        self._thread = threading.Thread(target=main, name="stop-port", daemon=True)
        self._thread.start()
        ready.wait()
        if failure:
            raise failure[0]
        log.info("stop port: POST http://%s:%d/stop (a listener of its own)",
                 f"[{self.host}]" if ":" in self.host else self.host, self.port)
        return self

    def close(self, timeout_s: float = 5.0) -> None:
        loop, thread = self.loop, self._thread
        if loop is None or thread is None:
            return
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout_s)
        self._thread = None
        self.loop = None

    # ------------------------------------------------------------------ connections
    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        key = id(writer)
        self._open += 1
        while self._open > self.max_connections and self._reading:  # the oldest still reading make room
            _, oldest = self._reading.popitem(last=False)
            self.evicted += 1
            oldest.transport.abort()
        self._reading[key] = writer
        try:
            try:
                async with asyncio.timeout(self.header_timeout_s):
                    head = await reader.readuntil(b"\r\n\r\n")
            except TimeoutError:
                await self._answer(writer, 408, {"detail": f"no complete request head within "
                                                           f"{self.header_timeout_s:g} s"})
                return
            except asyncio.LimitOverrunError:
                await self._answer(writer, 431, {"detail": f"request head larger than {MAX_HEAD_BYTES} bytes"})
                return
            except (asyncio.IncompleteReadError, ConnectionError):
                return
            self._reading.pop(key, None)  # a request in progress is never evicted
            try:
                method, target, headers = parse_head(head)
            except BadRequest as exc:
                await self._answer(writer, exc.status, {"detail": exc.detail})
                return
            status, body, extra = await self._handle(method, target, headers)
            await self._answer(writer, status, body, extra)
        except Exception:
            log.exception("stop port: a request failed")
            with contextlib.suppress(Exception):
                await self._answer(writer, 500, {"detail": "internal error; use the hardware emergency stop"})
        finally:
            self._reading.pop(key, None)
            self._open -= 1
            writer.close()

    async def _answer(self, writer: asyncio.StreamWriter, status: int, body: dict[str, Any],
                      extra: list[tuple[str, str]] | None = None) -> None:
        media = "application/json"
        if status >= 400:  # a refusal as RFC 9457 problem details, as on the main port
            kind = PROBLEM_KINDS.get(status, "bad-request")
            body = {"type": f"urn:sinecal:problem:{kind}", "title": REASONS.get(status, "Error"), "status": status,
                    "detail": str(body.get("detail", ""))}
            media = "application/problem+json"
        data = json.dumps(body).encode()
        head = [f"HTTP/1.1 {status} {REASONS.get(status, 'Error')}", f"Content-Type: {media}",
                f"Content-Length: {len(data)}", "Connection: close", "Cache-Control: no-store",
                *(f"{k}: {v}" for k, v in extra or [])]
        writer.write(("\r\n".join(head) + "\r\n\r\n").encode("latin-1") + data)
        with contextlib.suppress(Exception):
            async with asyncio.timeout(self.header_timeout_s):
                await writer.drain()

    # ------------------------------------------------------------------ requests
    def _page_origins(self, host: str) -> tuple[str, ...]:
        """``host:port`` of the station's own page (the main port) as seen through ``host``."""
        if self.page_port is None:
            return ()
        name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
        return (f"{name}:{self.page_port}",)

    async def _handle(self, method: str, target: str, headers: dict[str, str]
                      ) -> tuple[int, dict[str, Any], list[tuple[str, str]]]:
        url = urlsplit(target)
        if url.path != "/stop":
            return 404, {"detail": "the stop port serves POST /stop and GET /stop only"}, []
        host = headers.get("host", "")
        origin = headers.get("origin")
        why = host_refusal(host, self.names)
        if why is not None:
            log.warning("stop port: %s %s refused: %s", method[:16], url.path, why)
            return (400 if not host else 403), {"detail": why}, []
        why = cross_site_refusal(headers.get("sec-fetch-site"), origin, host, self._page_origins(host))
        if why is not None:
            return 403, {"detail": why}, []
        # the station's own page may read the answer (and sends its session: who stopped is recorded)
        cors = [("Access-Control-Allow-Origin", origin), ("Access-Control-Allow-Credentials", "true"),
                ("Vary", "Origin")] if origin is not None else []
        if method == "GET":
            return 200, self.stops.state(), cors
        if method != "POST":
            return 405, {"detail": f"method {method[:16]} not allowed: POST /stop or GET /stop"}, [
                ("Allow", "GET, POST")]
        log.warning("stop port: POST /stop (origin %s)", (origin or "none")[:80])
        client = parse_qs(url.query).get("client", [""])[0]
        source = "page" if client == "page" or headers.get("x-station-client") == "page" else "api"
        return 200, await self.stops.stop(source, headers), cors


