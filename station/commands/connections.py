"""Bounds on the daemon's HTTP connections, so that idle or slow clients cannot starve ``POST /stop``
or exhaust the process's file descriptors (used by ``station serve``):

* a **header timeout**: a connection that has not delivered a complete request head within
  ``header_timeout_s`` of opening (or of its previous response: keep-alive) is closed, even if it
  trickles bytes (uvicorn's keep-alive timer alone is cancelled by any byte).  It is the one rule for
  idle keep-alive connections too (uvicorn's own 5 s timer, which raced clients that keep an idle
  connection 5 s, e.g. httpx, is cancelled), announced in every response as ``Keep-Alive:
  timeout=N`` (:func:`keep_alive_header`).  A keep-alive connection is never closed mid-reuse: if
  the next request's first bytes are waiting in the kernel when the limit comes, its head gets
  ``header_timeout_s`` more (a socket closed with unread data answers with a reset); an idle one
  with nothing waiting is closed with a FIN, which a client reads as a clean close;
* a **connection cap**: beyond ``max_connections`` open connections, the oldest *idle* one is
  closed for each new one, so a new client, e.g. the emergency stop, is always served.  A
  connection is idle once its request was read and answered and nothing of its next one has come;
  failing those, a *silent* one (nothing received since it opened, not even in the kernel's
  buffer, for ``grace_s``) makes room.  A connection whose request head is arriving (read, or
  waiting in the kernel to be read) or whose request is in progress (a running request, the
  page's live event stream) is never closed for a newcomer: the header timeout bounds the first.
  Beyond ``ceiling`` (kept below the open-files limit) silent connections make room at any age;
* the **file-descriptor limit** raised from its soft to its hard value at the start, and the cap
  kept below it;
* repeated identical log records (e.g. "Too many open files" while accepting) are logged once per
  interval with a count (:class:`RepeatFilter`).

Behind the daemon's accept gate (``commands/gate.py``) a connection reaches the loop only once its
first bytes came: the silent ones are the gate's (``ConnectionBounds.held``), under the same rules.
"""

from __future__ import annotations

import array
import asyncio
import collections
import fcntl
import logging
import math
import resource
import termios
import threading
import time
from typing import Any, Protocol

from uvicorn.protocols.http.h11_impl import H11Protocol

log = logging.getLogger("station.serve")

WARN_INTERVAL_S = 10.0
FD_RESERVE = 256  # descriptors kept for the database, recordings, serial ports, worker pipes


def raise_fd_limit() -> int:
    """Raise RLIMIT_NOFILE's soft limit to its hard limit; returns the soft limit now in force."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or hard > soft:
        target = hard if hard != resource.RLIM_INFINITY else max(soft, 1 << 20)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError) as exc:
            log.warning("cannot raise the open-files limit from %d to %d: %s", soft, target, exc)
    return soft


def connection_cap(wanted: int, fd_limit: int) -> int:
    """The connection cap: ``wanted``, but below the descriptor limit with room for the rest."""
    return max(16, min(wanted, fd_limit - FD_RESERVE))


def pending_bytes(transport: asyncio.BaseTransport) -> int:
    """Bytes received by the kernel on ``transport``'s socket and not yet read (0 if unknown)."""
    sock = transport.get_extra_info("socket")
    return 0 if sock is None else pending_bytes_of(sock)


def pending_bytes_of(sock: Any) -> int:
    """Bytes received by the kernel on socket ``sock`` and not yet read (0 if unknown)."""
    buf = array.array("i", [0])
    try:
        fcntl.ioctl(sock.fileno(), termios.FIONREAD, buf, True)
    except (OSError, ValueError):
        return 0
    return int(buf[0])


def keep_alive_header(header_timeout_s: float) -> tuple[str, str]:
    """The response header announcing how long an idle keep-alive connection is kept at least, s
    (a whole second below the limit: the client's clock starts when the answer reaches it)."""
    return "Keep-Alive", f"timeout={max(1, math.ceil(header_timeout_s) - 1)}"


class HeadHook(Protocol):
    """What the server does with a request head as soon as it is read (``ConnectionBounds.on_head``)."""

    def __call__(self, scope: dict[str, Any], given: object = None) -> None:
        """On the server's loop, before the app runs the request; ``given``: what :meth:`early`
        returned for this connection's first request when the accept gate saw its head."""

    def early(self, method: str, path: str, headers: dict[str, str], loop: asyncio.AbstractEventLoop) -> object | None:
        """In the accept gate's thread (``commands/gate.py``), for a complete ``POST /stop`` head
        among a connection's first bytes, before the server's ``loop`` sees the connection."""


class ConnectionBounds:
    """State shared by every connection of one server: the idle ones and the silent new ones,
    oldest first.  ``ceiling``: open connections beyond which silent ones make room whatever their
    age (default twice the cap); ``grace_s``: how long a new connection may stay silent before it
    may make room below the ceiling.  ``held``: silent connections an accept gate holds outside the
    loop (``commands/gate.py``), counted against the cap too."""

    def __init__(self, max_connections: int, header_timeout_s: float, *, ceiling: int | None = None,
                 grace_s: float = 1.0) -> None:
        self.max_connections = max_connections
        self.header_timeout_s = header_timeout_s
        self.ceiling = max(max_connections, ceiling if ceiling is not None else 2 * max_connections)
        self.grace_s = grace_s
        self.idle: collections.OrderedDict[int, BoundedH11Protocol] = collections.OrderedDict()
        self.fresh: collections.OrderedDict[int, BoundedH11Protocol] = collections.OrderedDict()
        self.open = 0
        self.held = 0
        self.evicted = 0
        self.timed_out = 0
        self._warned = -math.inf
        self._count = threading.Lock()  # the counters: the loop and an accept gate's thread both count
        # called with a request's scope as soon as its head is read, before the app runs it (the
        # daemon hands POST /stop to the rig there: ``station.api.routes.system.stop_on_arrival``)
        self.on_head: HeadHook | None = None

    def count_timeout(self) -> None:
        with self._count:
            self.timed_out += 1

    def note_eviction(self) -> None:
        with self._count:
            self.evicted += 1
        now = time.monotonic()
        if now - self._warned >= WARN_INTERVAL_S:
            self._warned = now
            log.warning("connection cap reached (%d open): the oldest idle connections are closed for new ones "
                        "(%d so far, %d closed by the header timeout)", self.max_connections, self.evicted,
                        self.timed_out)

    def make_room(self) -> None:
        """Close idle, then silent, connections until the cap holds (or nothing may be closed)."""
        while self.open + self.held > self.max_connections:
            oldest = self._idle() or self._silent(any_age=self.open + self.held > self.ceiling)
            if oldest is None:
                return
            self.note_eviction()
            oldest._close()

    def _idle(self) -> BoundedH11Protocol | None:
        """The oldest idle connection with nothing of its next request waiting in the kernel (one
        whose request is waiting is reused just now: its head is arriving, and closing it would
        answer the client with a reset)."""
        while self.idle:
            conn = self.idle.popitem(last=False)[1]
            if pending_bytes(conn.transport) == 0:
                return conn
        return None

    def _silent(self, *, any_age: bool) -> BoundedH11Protocol | None:
        """The oldest new connection with nothing received, not even in the kernel (those whose
        request is waiting to be read leave the list: their head is arriving)."""
        now = time.monotonic()
        for key, conn in list(self.fresh.items()):
            if not any_age and now - conn.opened_at < self.grace_s:
                return None  # the rest are younger still
            if pending_bytes(conn.transport) > 0:
                del self.fresh[key]  # its request is arriving: never evicted
                continue
            del self.fresh[key]
            return conn
        return None

    def protocol(self) -> type[BoundedH11Protocol]:
        """uvicorn's ``http`` protocol class bound to these bounds."""
        return type("StationH11Protocol", (BoundedH11Protocol,), {"bounds": self})


class BoundedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with the header timeout and the connection cap of ``bounds``."""

    bounds: ConnectionBounds

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._head_timer: asyncio.TimerHandle | None = None
        self._counted = False  # in ``bounds.open``
        self._extended = False  # the head timer was extended once for a request found waiting
        self.opened_at = time.monotonic()  # an accept gate sets the time it accepted the connection
        self.given_stop: object = None  # what the accept gate's ``on_head.early`` returned for it

    def _busy(self) -> bool:
        return self.cycle is not None and not self.cycle.response_complete

    def _start_head_timer(self, since: float | None = None) -> None:
        """The header timeout from now, or from ``since`` (monotonic, s)."""
        if self._head_timer is not None:
            self._head_timer.cancel()
        self._extended = False
        left = self.bounds.header_timeout_s - (0.0 if since is None else time.monotonic() - since)
        self._head_timer = self.loop.call_later(max(0.0, left), self._head_timeout)

    def _mark_idle(self) -> None:
        """Answered, and nothing of a next request yet: the first to make room."""
        b = self.bounds
        b.fresh.pop(id(self), None)
        b.idle[id(self)] = self
        b.idle.move_to_end(id(self))
        self._start_head_timer()

    def _mark_arriving(self) -> None:
        """A request head is arriving: never closed for a newcomer (the header timer runs on)."""
        self.bounds.idle.pop(id(self), None)
        self.bounds.fresh.pop(id(self), None)

    def _mark_busy(self) -> None:
        self._mark_arriving()
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _close(self) -> None:
        """Close and stop counting it at once (its connection_lost comes a loop turn later)."""
        self._mark_busy()
        if self._counted:
            self._counted = False
            self.bounds.open -= 1
        self.transport.close()

    def _head_timeout(self) -> None:
        self._head_timer = None
        if self._busy() or self.transport.is_closing():
            return
        waiting = pending_bytes(self.transport) > 0
        if waiting and not self._extended and not self._head_begun():
            # an idle connection reused just at the limit: its request is in the kernel, unread; closing
            # now would reset it.  Its head gets the full time once more (then it is closed like any other)
            self._head_timer = self.loop.call_later(self.bounds.header_timeout_s, self._head_timeout)
            self._extended = True
            return
        self.bounds.count_timeout()
        self._close()  # nothing unread in the kernel: our FIN, no reset (a head too slow may be reset)

    def _head_begun(self) -> bool:
        """Part of a request head has been read (h11 holds it, waiting for the rest)."""
        return bool(self.conn.trailing_data[0])

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        b = self.bounds
        b.open += 1
        self._counted = True
        b.fresh[id(self)] = self  # not idle: its request has not been read and answered yet
        self._start_head_timer(since=self.opened_at)  # (a connection held by an accept gate: since then)
        b.make_room()

    def connection_lost(self, exc: Exception | None) -> None:
        self._mark_busy()
        if self._counted:
            self._counted = False
            self.bounds.open -= 1
        super().connection_lost(exc)

    def handle_events(self) -> None:
        cycle = self.cycle
        super().handle_events()
        hook = self.bounds.on_head
        if hook is not None and self.cycle is not None and self.cycle is not cycle:  # a new request's head
            given, self.given_stop = self.given_stop, None  # the gate's, for the first request only
            try:
                hook(self.cycle.scope, given)  # type: ignore[arg-type]
            except Exception:
                log.exception("handling a request head on its arrival failed (the app still handles the request)")

    def data_received(self, data: bytes) -> None:
        self._mark_arriving()
        super().data_received(data)
        if self._busy():
            self._mark_busy()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._unset_keepalive_if_required()  # the header timer is the one rule for an idle connection
        if not self.transport.is_closing() and not self._busy():
            if self.conn.trailing_data[0]:  # part of the next request's head came with the last one
                self._mark_arriving()
                self._start_head_timer()
            else:
                self._mark_idle()


class RepeatFilter(logging.Filter):
    """Passes a log record unless the same (logger, level, message) passed within ``interval_s``;
    the next one after the interval says how many were held back."""

    def __init__(self, interval_s: float = 10.0, max_keys: int = 1000) -> None:
        super().__init__()
        self.interval_s = interval_s
        self.max_keys = max_keys
        self._seen: dict[tuple[str, int, str], tuple[float, int]] = {}
        self._lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        try:
            text = record.getMessage()
        except Exception:
            text = str(record.msg)
        key = (record.name, record.levelno, text[:300])
        now = time.monotonic()
        with self._lock:
            last = self._seen.get(key)
            if last is not None and now - last[0] < self.interval_s:
                self._seen[key] = (last[0], last[1] + 1)
                return False
            held = last[1] if last is not None else 0
            if len(self._seen) >= self.max_keys:
                self._seen.clear()
            self._seen[key] = (now, 0)
        if held:
            record.msg = f"{record.msg} [{held} identical message(s) in the last {self.interval_s:g} s not logged]"
        return True


def install_repeat_filter(interval_s: float = 10.0) -> RepeatFilter:
    """On every handler of the root logger (the daemon logs through it)."""
    f = RepeatFilter(interval_s)
    for h in logging.getLogger().handlers:
        h.addFilter(f)
    return f
