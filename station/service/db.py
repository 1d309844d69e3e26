"""The daemon's door to its database from the web side's event loop, which never waits on SQLite.

* **Reads** run in a small thread pool of their own on the store's read connection (WAL: a writer,
  ours or another process's, does not block them) and are awaited with a bound: a database that
  does not answer in time gives :class:`DatabaseBusyError` (HTTP 503), never a stalled loop.
* **Writes** go, in the order they were made, to one writer thread.  A write the database does not
  take now (locked by another process beyond its busy timeout, disk full) stays at the head of the
  queue and is retried with a growing pause until it is taken; nothing behind it overtakes it.
  ``post`` hands a write over and returns at once (run progress, the emergency stop's record);
  ``call`` awaits one with a bound and withdraws it if it has not started by then (a run's first
  row, an acknowledgement).  Updates of one run still waiting are merged into one write.
  :meth:`DbAccess.overlay` gives readers the latest values this daemon gave each run (kept for the
  most recent runs), so that a run's state read back is the latest one whether or not the database
  has taken it yet (a row read just before a write and a queue looked at just after it cannot
  combine into an older state).

Nothing on the emergency stop's path goes through here (see ``docs/safety.md``).
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import logging
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

from station.lab.store import Store
from station.service.errors import DatabaseBusyError

log = logging.getLogger(__name__)

T = TypeVar("T")

READ_TIMEOUT_S = 3.0  # a read the database does not answer within this is refused (503)
WRITE_WAIT_S = 5.0  # a caller awaiting its write gives up after this (the write is withdrawn)
RECENT_RUNS = 256  # runs whose latest values are kept for readers
MAX_READS_IN_FLIGHT = 32  # beyond this, reads are refused at once instead of queueing
RETRY_FIRST_S = 0.1
RETRY_MAX_S = 5.0


@dataclass(eq=False)
class _Write:
    fn: Callable[[Store], Any] | None  # None: a merged update of one run (``values``)
    run_id: str | None = None
    values: dict[str, Any] = field(default_factory=dict)
    future: concurrent.futures.Future[Any] | None = None
    run_values: tuple[str, dict[str, Any]] | None = None  # a run's values ``fn`` writes (for readers, once taken)
    started: bool = False
    withdrawn: bool = False


class DbAccess:
    """Reads in a pool, writes through one ordered, retrying writer thread; ``start`` then ``close``."""

    def __init__(self, store: Store, *, read_threads: int = 2) -> None:
        self.store = store
        self._reads = concurrent.futures.ThreadPoolExecutor(read_threads, thread_name_prefix="db-read")
        self._reads_in_flight = 0
        self._queue: collections.deque[_Write] = collections.deque()
        self._open_updates: dict[str, _Write] = {}  # run id -> its update not yet started
        self._latest: collections.OrderedDict[str, dict[str, Any]] = collections.OrderedDict()
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self._closing = False
        self.last_error: str | None = None  # why the write at the head of the queue waits (None: it does not)
        self.failed_since: float | None = None
        self._head_since: float | None = None  # monotonic time the write at the head was first tried

    # ------------------------------------------------------------------ life cycle
    def start(self) -> DbAccess:
        if self._thread is None:
            self._thread = threading.Thread(target=self._writer, name="db-writer", daemon=True)
            self._thread.start()
        return self

    def close(self, timeout_s: float = 5.0) -> int:
        """Write what is queued (waiting up to ``timeout_s``), end the threads; returns the number of
        writes left unwritten (logged)."""
        deadline = time.monotonic() + timeout_s
        if self._thread is not None:
            self.flush(timeout_s)
        with self._cond:
            self._closing = True
            left = len(self._queue)
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(max(0.0, deadline - time.monotonic()) + 0.5)
        self._reads.shutdown(wait=False, cancel_futures=True)
        if left:
            log.error("%d database write(s) not taken before the end (%s); the database misses them",
                      left, self.last_error)
        return left

    def flush(self, timeout_s: float = 5.0) -> bool:
        """Wait (blocking, from any thread but the writer) until every queued write is taken or
        ``timeout_s`` passed; True if none is left."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._queue and time.monotonic() < deadline:
                self._cond.wait(min(0.1, max(0.0, deadline - time.monotonic())))
            return not self._queue

    @property
    def stalled_s(self) -> float:
        """How long the write at the head of the queue has been waiting for the database, s."""
        with self._cond:
            return 0.0 if self._head_since is None or not self._queue else time.monotonic() - self._head_since

    @property
    def backlog(self) -> int:
        """Writes waiting for the database."""
        with self._cond:
            return len(self._queue)

    # ------------------------------------------------------------------ reads
    async def read(self, fn: Callable[[Store], T], *, timeout_s: float = READ_TIMEOUT_S) -> T:
        """``fn(store)`` in the read pool, awaited at most ``timeout_s``; DatabaseBusyError otherwise."""
        if self._reads_in_flight >= MAX_READS_IN_FLIGHT:
            raise DatabaseBusyError("the database is not answering (too many reads waiting); try again")
        self._reads_in_flight += 1
        try:
            fut = self._reads.submit(fn, self.store)
            return await asyncio.wait_for(asyncio.wrap_future(fut), timeout_s)
        except TimeoutError:
            raise DatabaseBusyError(f"the database did not answer within {timeout_s:g} s (locked by another "
                                    "process?); try again") from None
        except RuntimeError as exc:  # the pool is shut down
            raise DatabaseBusyError(f"the database is closed ({exc})") from None
        finally:
            self._reads_in_flight -= 1

    # ------------------------------------------------------------------ writes
    def post(self, fn: Callable[[Store], Any]) -> None:
        """Queue a write; it is retried until the database takes it.  Returns at once."""
        self._enqueue(_Write(fn))

    def _remember(self, run_id: str, values: dict[str, Any]) -> None:
        """(Under the lock.)  Merge into the run's latest values, for readers."""
        self._latest[run_id] = {**self._latest.pop(run_id, {}), **values}
        while len(self._latest) > RECENT_RUNS:
            self._latest.popitem(last=False)

    def update_run(self, run_id: str, values: dict[str, Any]) -> None:
        """Queue an update of a run's row, merged with one of the same run still waiting."""
        if not values:
            return
        with self._cond:
            self._remember(run_id, values)  # written, however long the database takes: readers see it now
            w = self._open_updates.get(run_id)
            if w is not None and not w.started:
                w.values.update(values)
                return
            w = _Write(None, run_id, dict(values))
            self._open_updates[run_id] = w
            self._queue.append(w)
            self._cond.notify_all()

    def overlay(self, run_id: str) -> dict[str, Any]:
        """The latest values this daemon gave the run (applied over a row read back); call it after
        the read."""
        with self._cond:
            return dict(self._latest.get(run_id, {}))

    async def call(self, fn: Callable[[Store], T], *, timeout_s: float = WRITE_WAIT_S,
                   run_values: tuple[str, dict[str, Any]] | None = None) -> T:
        """Queue a write and await its result; if it has not started within ``timeout_s`` it is
        withdrawn and DatabaseBusyError raised (one that started is awaited to its end).
        ``run_values``: (run id, values) that ``fn`` writes into the run's row, given to readers
        once it is taken."""
        w = _Write(fn, future=concurrent.futures.Future(), run_values=run_values)
        self._enqueue(w)
        assert w.future is not None
        try:
            return await asyncio.wait_for(asyncio.shield(asyncio.wrap_future(w.future)), timeout_s)
        except TimeoutError:
            with self._cond:
                if not w.started:
                    w.withdrawn = True
                    raise DatabaseBusyError(
                        f"the database did not take the change within {timeout_s:g} s "
                        f"({self.last_error or 'writes queued before it'}); nothing was changed") from None
            return await asyncio.wrap_future(w.future)

    def _enqueue(self, w: _Write) -> None:
        with self._cond:
            if self._closing:
                raise DatabaseBusyError("the database is closing")
            self._queue.append(w)
            self._cond.notify_all()

    def _writer(self) -> None:
        pause = RETRY_FIRST_S
        while True:
            with self._cond:
                while not self._queue and not self._closing:
                    self._cond.wait()
                if not self._queue:
                    return
                w = self._queue[0]
                if w.withdrawn:
                    self._queue.popleft()
                    self._head_since = None
                    continue
                w.started = True
                if self._head_since is None:
                    self._head_since = time.monotonic()
                if w.run_id is not None and self._open_updates.get(w.run_id) is w:
                    del self._open_updates[w.run_id]
            try:
                if w.fn is None:
                    assert w.run_id is not None
                    self.store.update_run(w.run_id, **w.values)
                    result = None
                else:
                    result = w.fn(self.store)
            except sqlite3.Error as exc:
                with self._cond:
                    w.started = False
                    if w.run_id is not None and w.run_id not in self._open_updates:
                        self._open_updates[w.run_id] = w  # later updates merge into it again
                    if self.failed_since is None:
                        self.failed_since = time.time()
                        log.error("the database does not take writes (%s); %d queued, retried", exc,
                                  len(self._queue))
                    self.last_error = f"{type(exc).__name__}: {exc}"
                    if self._closing:
                        return
                    self._cond.wait(pause)
                pause = min(RETRY_MAX_S, pause * 2)
                continue
            except Exception as exc:  # the caller's refusal or a programming error: never block the queue
                if w.future is None:  # nobody waits for it: the log is the only place it can show
                    log.exception("database write failed")
                else:  # the waiting caller gets it and answers for it (e.g. a 404 for an unknown user)
                    log.debug("database write refused: %s", exc, exc_info=True)
                with self._cond:
                    self._queue.popleft()
                    self._head_since = None
                    self._cond.notify_all()
                if w.future is not None:
                    w.future.set_exception(exc)
                continue
            with self._cond:
                self._queue.popleft()
                if w.run_values is not None:
                    self._remember(*w.run_values)
                if self.failed_since is not None:
                    log.warning("the database takes writes again (after %.1f s)", time.time() - self.failed_since)
                self.failed_since, self.last_error, self._head_since = None, None, None
                self._cond.notify_all()
            pause = RETRY_FIRST_S
            if w.future is not None:
                w.future.set_result(result)
