"""The main port's accept gate (used by ``station serve``): a thread of its own accepts the web
server's connections and holds each one, at the cost of a descriptor and a selector entry, until its
first bytes arrive; only then is it handed to uvicorn's event loop.

Without it the server's loop accepts every new connection itself (a transport, a protocol object,
timers, each in Python), so a flood of idle connections keeps the loop busy for seconds on a loaded
machine while new ones wait in the kernel's accept backlog, and once that is full the kernel drops
their handshakes (a client then tries again 1, 3, 7 s later): a ``POST /stop`` sent meanwhile
arrives late.  With the gate:

* the backlog is drained at once, by a thread that does nothing else: no new connection waits
  behind the loop's work;
* a silent connection costs the loop nothing; the gate keeps :mod:`connections`' rules for it: the
  **header timeout** (closed ``header_timeout_s`` after it opened, with our FIN: it sent nothing),
  the **connection cap** (beyond ``max_connections``, the loop first closes its oldest idle
  connections; failing those, the gate closes its oldest silent ones past ``grace_s``, at any age
  beyond ``ceiling``), and a refused ``accept`` (out of descriptors) never spins;
* a connection whose first bytes are a complete ``POST /stop`` head is recognised here and the
  stop handed to the rig at once (``ConnectionBounds.on_head.early``: the route's own checks), before
  the connection reaches the loop; the route then answers with that very stop.

A connection handed over keeps the time it opened (its header timeout counts from then), and the
loop's :class:`~station.commands.connections.BoundedH11Protocol` carries on with it as with one it
accepted itself."""

from __future__ import annotations

import asyncio
import collections
import contextlib
import errno
import logging
import selectors
import socket
import sys
import threading
import time
from typing import Any
from urllib.parse import unquote, urlsplit

import uvicorn
from uvicorn.config import STARTUP_FAILURE

from station.commands.connections import ConnectionBounds, pending_bytes_of
from station.rigproc.stopport import BadRequest, parse_head
from station.service.priority import Priority, raise_priority

log = logging.getLogger("station.serve")

PEEK_BYTES = 8192  # the first bytes looked at for a stop's head (the stop port's head limit too)
ACCEPT_BATCH = 256  # connections accepted in one go before the gate looks at the rest
PAUSE_S = 0.5  # accepting pauses this long when the process is out of descriptors
OUT_OF_DESCRIPTORS = (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)


def bind(host: str | None, port: int, backlog: int) -> list[socket.socket]:
    """Listening sockets for ``host``:``port`` (every address the name resolves to; port 0: one
    free port for all), non-blocking.  OSError if one cannot be bound."""
    infos = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    seen: set[tuple[int, Any]] = set()
    socks: list[socket.socket] = []
    try:
        for family, kind, proto, _, addr in infos:
            if (family, addr) in seen:
                continue
            seen.add((family, addr))
            sock = socket.socket(family, kind, proto)
            socks.append(sock)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if family == socket.AF_INET6:
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            if port == 0 and len(socks) > 1:  # the same free port on every address
                addr = (addr[0], socks[0].getsockname()[1], *addr[2:])
            sock.bind(addr)
            sock.listen(backlog)
            sock.setblocking(False)
    except OSError:
        for s in socks:
            s.close()
        raise
    return socks


def stop_head(data: bytes) -> tuple[str, str, dict[str, str]] | None:
    """(method, path, headers) when ``data`` begins with a complete ``POST /stop`` request head;
    None for anything else (the loop then reads it as any request)."""
    if not data.startswith(b"POST /"):
        return None
    end = data.find(b"\r\n\r\n")
    if end < 0:
        return None
    try:
        method, target, headers = parse_head(data[:end + 4])
    except BadRequest:
        return None
    path = unquote(urlsplit(target).path)
    return (method, path, headers) if path == "/stop" else None


def gate_priority(rig_priority: Priority) -> Priority:
    """What the gate's thread asks for, given ``service.rig_priority``: a raised priority at most (a
    thread that accepts a flood must not take a core from everything else, as a real-time one could)."""
    return "normal" if rig_priority == "normal" else "raised"


class AcceptGate:
    """Accepts on ``listeners`` in a thread of its own and holds each new connection until its
    first bytes; ``hand(sock, opened_at, early)`` is then called on ``loop`` (``early``: what
    ``bounds.on_head.early`` returned for a stop's head, else None).  ``priority``: what its thread
    asks for (logged: what it got)."""

    def __init__(self, listeners: list[socket.socket], bounds: ConnectionBounds, loop: asyncio.AbstractEventLoop,
                 hand: Any, priority: Priority = "normal") -> None:
        self.listeners = listeners
        self.priority = priority
        self.bounds = bounds
        self.loop = loop
        self.hand = hand
        self.held: collections.OrderedDict[int, tuple[socket.socket, float]] = collections.OrderedDict()
        self.accepted = 0
        self.handed = 0
        self.early_stops = 0
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._closing = False
        self._paused_until: float | None = None
        self._room_asked = False  # the loop was asked to close idle connections and has not yet
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ lifetime
    def start(self) -> AcceptGate:
        self._wake_r.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        for sock in self.listeners:
            self._sel.register(sock, selectors.EVENT_READ, "listen")
        self._thread = threading.Thread(target=self._run, name="accept-gate", daemon=True)
        self._thread.start()
        return self

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop accepting; close the listeners and the connections still silent."""
        self._closing = True
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        for sock in self.listeners:
            sock.close()
        for sock, _ in self.held.values():
            sock.close()
        self.held.clear()
        self.bounds.held = 0
        self._sel.close()
        self._wake_r.close()
        self._wake_w.close()

    # ------------------------------------------------------------------ the thread
    def _run(self) -> None:
        if self.priority != "normal":
            raise_priority("accept-gate", self.priority)
        while not self._closing:
            try:
                events = self._sel.select(self._wait_s())
                for key, _ in events:
                    if key.data == "listen":
                        self._accept(key.fileobj)  # type: ignore[arg-type]
                    elif key.data == "wake":
                        with contextlib.suppress(OSError):
                            self._wake_r.recv(64)
                    else:
                        self._first_bytes(key.fileobj)  # type: ignore[arg-type]
                self._expire()
                self._make_room()
                self._resume()
            except Exception:  # never leaves the port without its acceptor
                log.exception("the accept gate failed in one turn (it carries on)")
                time.sleep(0.05)

    def _wait_s(self) -> float:
        """Until the oldest silent connection's header timeout, the end of its grace when beyond the
        cap, or the end of a pause (at most 1 s; never 0 for a grace already past: no spinning while
        the loop closes idle connections)."""
        now = time.monotonic()
        wait = 1.0
        if self.held:
            _, opened = next(iter(self.held.values()))
            wait = min(wait, opened + self.bounds.header_timeout_s - now)
            of_age = opened + self.bounds.grace_s
            if of_age > now and self.bounds.open + len(self.held) > self.bounds.max_connections:
                wait = min(wait, of_age - now)
        if self._paused_until is not None:
            wait = min(wait, self._paused_until - now)
        return max(0.0, wait)

    def _accept(self, listener: socket.socket) -> None:
        for _ in range(ACCEPT_BATCH):
            try:
                sock, _ = listener.accept()
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                if exc.errno in OUT_OF_DESCRIPTORS:
                    log.error("accepting a connection: %s (open: %d, silent: %d)", exc.strerror,
                              self.bounds.open, len(self.held))
                    if not self._drop_oldest_silent():
                        self._pause()
                        break
                continue  # e.g. ECONNABORTED: the client gave up in the backlog
            sock.setblocking(False)
            now = time.monotonic()
            try:
                self._sel.register(sock, selectors.EVENT_READ, "conn")
            except (OSError, ValueError):
                sock.close()
                continue
            self.held[sock.fileno()] = (sock, now)
            self.accepted += 1
            self.bounds.held = len(self.held)
            self._make_room()

    def _first_bytes(self, sock: socket.socket) -> None:
        fd = sock.fileno()
        entry = self.held.pop(fd, None)
        self._sel.unregister(sock)
        self.bounds.held = len(self.held)
        if entry is None:  # pragma: no cover - every registered connection is held
            sock.close()
            return
        try:
            data = sock.recv(PEEK_BYTES, socket.MSG_PEEK)
        except (BlockingIOError, InterruptedError):  # nothing after all: held on
            self._sel.register(sock, selectors.EVENT_READ, "conn")
            self.held[fd] = entry
            self.held.move_to_end(fd, last=False)  # keeps its age (approximately: among the oldest)
            self.bounds.held = len(self.held)
            return
        except OSError:
            sock.close()
            return
        if not data:  # the client closed without a word
            sock.close()
            return
        early = None
        hook = self.bounds.on_head
        head = stop_head(data) if hook is not None else None
        if head is not None and hook is not None:
            try:
                early = hook.early(*head, self.loop)
            except Exception:
                log.exception("handing a stop to the rig as its head arrived failed (the app still handles it)")
            if early is not None:
                self.early_stops += 1
        try:
            self.loop.call_soon_threadsafe(self.hand, sock, entry[1], early)
            self.handed += 1
        except RuntimeError:  # the loop has ended
            sock.close()

    def _expire(self) -> None:
        """Close the silent connections past the header timeout (they sent nothing: a clean FIN)."""
        now = time.monotonic()
        limit = self.bounds.header_timeout_s
        while self.held:
            fd, (sock, opened) = next(iter(self.held.items()))
            if now - opened < limit:
                break
            self.bounds.count_timeout()  # counted before the FIN: whoever sees the close sees the count
            self._drop(fd, sock)

    def _make_room(self) -> None:
        """Beyond the cap: the loop closes its idle connections first; for what they cannot make up,
        the oldest silent ones past their grace (at any age beyond the ceiling) are closed here."""
        b = self.bounds
        excess = b.open + len(self.held) - b.max_connections
        if excess <= 0:
            return
        idle = len(b.idle)
        if idle and not self._room_asked:  # once until the loop has done it
            self._room_asked = True
            with contextlib.suppress(RuntimeError):
                self.loop.call_soon_threadsafe(self._loop_makes_room)
        any_age = b.open + len(self.held) > b.ceiling
        now = time.monotonic()
        for _ in range(excess - idle):
            if not self.held:
                return
            fd, (sock, opened) = next(iter(self.held.items()))
            if not any_age and now - opened < b.grace_s:
                return
            if pending_bytes_of(sock) > 0:  # its first bytes are here: handed over on this turn
                return
            b.note_eviction()  # counted before the FIN
            self._drop(fd, sock)

    def _loop_makes_room(self) -> None:
        self._room_asked = False
        self.bounds.make_room()

    def _drop_oldest_silent(self) -> bool:
        if not self.held:
            return False
        fd, (sock, _) = next(iter(self.held.items()))
        self.bounds.note_eviction()  # counted before the FIN
        self._drop(fd, sock)
        return True

    def _drop(self, fd: int, sock: socket.socket) -> None:
        self.held.pop(fd, None)
        self.bounds.held = len(self.held)
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(sock)
        sock.close()

    def _pause(self) -> None:
        self._paused_until = time.monotonic() + PAUSE_S
        for sock in self.listeners:
            with contextlib.suppress(KeyError, ValueError):
                self._sel.unregister(sock)

    def _resume(self) -> None:
        if self._paused_until is None or time.monotonic() < self._paused_until:
            return
        self._paused_until = None
        for sock in self.listeners:
            self._sel.register(sock, selectors.EVENT_READ, "listen")


class GatedServer(uvicorn.Server):
    """uvicorn with its listening sockets served by an :class:`AcceptGate` (its loop sees a
    connection once its first bytes have come); ``bounds``: the server's :class:`ConnectionBounds`
    (``config.http`` must be ``bounds.protocol()``); ``priority``: what the gate's thread asks for."""

    def __init__(self, config: uvicorn.Config, bounds: ConnectionBounds, priority: Priority = "normal") -> None:
        super().__init__(config)
        self.bounds = bounds
        self.priority = priority
        self.gate: AcceptGate | None = None
        self.listeners: list[socket.socket] = []
        self._adopting: set[asyncio.Task[Any]] = set()

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        config = self.config
        if sockets is not None or config.uds is not None or config.fd is not None or config.ssl is not None:
            await super().startup(sockets)  # not a plain TCP port: uvicorn's own accept
            return
        await self.lifespan.startup()
        if self.lifespan.should_exit:
            sys.exit(STARTUP_FAILURE)
        try:
            self.listeners = bind(config.host, config.port, config.backlog)
        except OSError as exc:
            log.error("%s", exc)
            await self.lifespan.shutdown()
            sys.exit(STARTUP_FAILURE)
        self.servers = []
        self.gate = AcceptGate(self.listeners, self.bounds, asyncio.get_running_loop(), self._adopt,
                               self.priority).start()
        self._log_started_message(self.listeners)
        self.started = True

    def bound_sockets(self) -> list[socket.socket]:
        """The listening sockets, the gate's or uvicorn's own."""
        return self.listeners or [s for server in self.servers for s in (server.sockets or ())]

    def _adopt(self, sock: socket.socket, opened_at: float, early: object) -> None:
        """On the loop: a connection from the gate becomes uvicorn's, as if accepted here."""
        config = self.config

        def protocol() -> asyncio.Protocol:
            proto = config.http_protocol_class(config=config, server_state=self.server_state,  # type: ignore[call-arg]
                                               app_state=self.lifespan.state)
            proto.opened_at = opened_at  # type: ignore[attr-defined]
            proto.given_stop = early  # type: ignore[attr-defined]
            return proto

        if self.should_exit:
            sock.close()
            return
        task = asyncio.get_running_loop().create_task(self._connect(protocol, sock))
        self._adopting.add(task)
        task.add_done_callback(self._adopting.discard)

    @staticmethod
    async def _connect(protocol: Any, sock: socket.socket) -> None:
        try:
            await asyncio.get_running_loop().connect_accepted_socket(protocol, sock)
        except OSError:  # the client left meanwhile
            sock.close()

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        if self.gate is not None:
            self.gate.close()
            self.gate = None
        await super().shutdown(sockets)
