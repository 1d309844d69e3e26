"""Logins that resist guessing, and that never slow anybody else down.

* **Lock-out** (:class:`LoginThrottle`): failed logins are counted per user name and per client
  address.  After ``FREE_FAILURES`` in a row, each further failure locks that name (or address) out
  for a growing time: ``BASE_LOCK_S`` doubled with each failure, at most ``MAX_LOCK_S``.  While
  locked, a login is refused with the time it is lifted, whatever the password; the password is
  still checked against the name's hash (or a hash nobody has) in the bounded pool below, so that a
  lock-out cannot be told by the time a refusal takes, and the answer is not used.  A success clears
  the name's count (not the address's).  Each lock-out is logged and audited
  (``user.login_locked``), listed for administrators (``GET /logins/locks``) and lifted by them
  (``DELETE /logins/locks/{key}``) or by time.  Counts live in the daemon's memory; each lock-out
  (its key, failures and end) is also kept in the database (``login_locks``, written through the
  daemon's writer) and loaded at start, so that a restart neither lifts a lock-out nor starts its
  doubling again.  Counts below the first lock-out are not kept (a flood of names writes nothing).
* **The password check's own pool** (:class:`PasswordPool`): the scrypt check (~0.1 s of CPU, 16 MiB)
  runs in ``WORKERS`` threads of its own with at most ``QUEUE`` logins waiting; a login beyond that
  is refused at once ("too many logins at once"), before it reads anything: a flood of logins holds
  at most ``WORKERS + QUEUE`` of the database's reads in flight, never the bound every other
  request shares.  The database's read pool never runs a password check.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Callable, Iterable
from dataclasses import dataclass
from typing import Any

log = logging.getLogger(__name__)

FREE_FAILURES = 5  # failures in a row before the first lock-out
BASE_LOCK_S = 2.0  # the first lock-out; doubled with each further failure
MAX_LOCK_S = 900.0
WORKERS = 2
QUEUE = 8


@dataclass
class _Count:
    failures: int = 0
    locked_until: float = 0.0


class LoginThrottle:
    """Failure counts and lock-outs per key (``user:<name>`` or ``client:<address>``).  ``save(key,
    failures, locked_until)`` keeps a lock-out (failures 0: forget the key); :meth:`load` puts kept
    ones back."""

    def __init__(self, clock: Any = time.time, save: Callable[[str, int, float], None] | None = None) -> None:
        self._clock = clock
        self._counts: dict[str, _Count] = {}
        self._save = save

    def load(self, rows: Iterable[tuple[str, int, float]]) -> None:
        """The lock-outs kept (key, failures, locked until in UNIX s) back in memory."""
        for key, failures, until in rows:
            self._counts[key] = _Count(int(failures), float(until))

    def _keep(self, key: str, c: _Count | None) -> None:
        if self._save is not None:
            try:
                self._save(key, 0 if c is None else c.failures, 0.0 if c is None else c.locked_until)
            except Exception:  # the lock-out holds in memory whatever the database does
                log.exception("login lock-out of %s not kept in the database", key)

    def refusal(self, keys: list[str]) -> str | None:
        """Why a login with these keys is refused now (a lock-out in force), or None."""
        now = self._clock()
        for k in keys:
            c = self._counts.get(k)
            if c is not None and c.locked_until > now:
                at = time.strftime("%H:%M:%S UTC", time.gmtime(c.locked_until))
                return (f"too many failed logins for this {k.split(':', 1)[0]}: locked until {at} "
                        f"({c.locked_until - now:.0f} s; an administrator can lift it)")
        return None

    def failed(self, keys: list[str]) -> list[tuple[str, float]]:
        """Count a failure; returns the keys it locked out now, with the lock's length (s)."""
        now, locked = self._clock(), []
        for k in keys:
            c = self._counts.setdefault(k, _Count())
            c.failures += 1
            if c.failures > FREE_FAILURES:
                length = min(MAX_LOCK_S, BASE_LOCK_S * 2 ** (c.failures - FREE_FAILURES - 1))
                c.locked_until = now + length
                locked.append((k, length))
                self._keep(k, c)
        if len(self._counts) > 100_000:  # bounded memory under a flood of names: the oldest unlocked go
            for k in [k for k, c in self._counts.items() if c.locked_until <= now][:50_000]:
                del self._counts[k]
        return locked

    def succeeded(self, user_key: str) -> None:
        c = self._counts.pop(user_key, None)
        if c is not None and c.failures > FREE_FAILURES:
            self._keep(user_key, None)

    def locks(self) -> list[dict[str, Any]]:
        now = self._clock()
        return [{"key": k, "failures": c.failures, "locked_until": c.locked_until}
                for k, c in sorted(self._counts.items()) if c.locked_until > now]

    def lift(self, key: str) -> bool:
        c = self._counts.pop(key, None)
        if c is not None and c.failures > FREE_FAILURES:
            self._keep(key, None)
        return c is not None


class PasswordPool:
    """The scrypt checks' own threads, with a bounded queue (module docstring)."""

    def __init__(self, workers: int = WORKERS, queue: int = QUEUE) -> None:
        self._pool = concurrent.futures.ThreadPoolExecutor(workers, thread_name_prefix="password-check")
        self._slots = asyncio.Semaphore(workers + queue)
        self._limit = workers + queue

    def full(self) -> bool:
        return self._slots.locked()

    @contextlib.asynccontextmanager
    async def admitted(self) -> AsyncIterator[bool]:
        """A login's place (held for its look-up and its check), or False at once when all are taken."""
        if self._slots.locked():
            yield False
            return
        async with self._slots:
            yield True

    async def check(self, fn: Any, *args: Any) -> Any:
        """``fn(*args)`` in the pool's threads, for a login :meth:`admitted`."""
        return await asyncio.get_running_loop().run_in_executor(self._pool, fn, *args)

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
