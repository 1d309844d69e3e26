"""Logins that resist guessing, and that never slow anybody else down.

* **Lock-out** (:class:`LoginThrottle`): failed logins are counted per user name and per client
  address.  After ``FREE_FAILURES`` in a row, each further failure locks that name (or address) out
  for a growing time: ``BASE_LOCK_S`` doubled with each failure, at most ``MAX_LOCK_S``.  While
  locked, a login is refused at once with the time it is lifted (no password is checked: a guess
  costs nothing and reveals nothing).  A success clears the name's count (not the address's).  Each
  lock-out is logged and audited (``user.login_locked``), listed for administrators (``GET
  /logins/locks``) and lifted by them (``DELETE /logins/locks/{key}``) or by time.  Counts live in
  the daemon's memory: a restart forgets them (a lock-out is short by design; the audit keeps them).
* **The password check's own pool** (:class:`PasswordPool`): the scrypt check (~0.1 s of CPU, 16 MiB)
  runs in ``WORKERS`` threads of its own with at most ``QUEUE`` logins waiting; a login beyond that
  is refused at once ("too many logins at once").  The database's read pool, which every other
  request needs, never runs a password check.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import time
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
    """Failure counts and lock-outs per key (``user:<name>`` or ``client:<address>``)."""

    def __init__(self, clock: Any = time.time) -> None:
        self._clock = clock
        self._counts: dict[str, _Count] = {}

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
        if len(self._counts) > 100_000:  # bounded memory under a flood of names: the oldest unlocked go
            for k in [k for k, c in self._counts.items() if c.locked_until <= now][:50_000]:
                del self._counts[k]
        return locked

    def succeeded(self, user_key: str) -> None:
        self._counts.pop(user_key, None)

    def locks(self) -> list[dict[str, Any]]:
        now = self._clock()
        return [{"key": k, "failures": c.failures, "locked_until": c.locked_until}
                for k, c in sorted(self._counts.items()) if c.locked_until > now]

    def lift(self, key: str) -> bool:
        return self._counts.pop(key, None) is not None


class PasswordPool:
    """The scrypt checks' own threads, with a bounded queue (module docstring)."""

    def __init__(self, workers: int = WORKERS, queue: int = QUEUE) -> None:
        self._pool = concurrent.futures.ThreadPoolExecutor(workers, thread_name_prefix="password-check")
        self._slots = asyncio.Semaphore(workers + queue)
        self._limit = workers + queue

    def full(self) -> bool:
        return self._slots.locked()

    async def run(self, fn: Any, *args: Any) -> Any:
        if self._slots.locked():
            return None
        async with self._slots:
            return await asyncio.get_running_loop().run_in_executor(self._pool, fn, *args)

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
