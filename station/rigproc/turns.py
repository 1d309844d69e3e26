"""The drive's one link, shared by turns: the stop first, the watchdog refresh next, the web process last.

The Modbus client pairs a reply with the one request in flight, so the rig process's users of the
link (the stop and its read-back, the watchdog keeper, the web process's forwarded reads and writes)
take turns.  A first-come queue would let a stop or a refresh wait behind every question the web
process asked before it; under load (a flooded web process polling the drive, a starved emulator)
that queue was measured long enough for the drive's watchdog to expire.  Here a waiting stop goes
before a waiting refresh, and both before the web process's exchanges; an exchange already on the
wire is never interrupted (the drive would answer it anyway), so a stop waits at most for one.

Who asks is a context variable (``urgency``), set by the keeper task for its whole life and by the
stop for its own exchanges: the drivers' code in between needs no parameter for it.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import heapq
import itertools
from collections.abc import AsyncIterator, Iterator, Sequence
from enum import IntEnum

from drivers.motor.transport import RegisterTransport


class Urgency(IntEnum):
    """Whose exchange goes first on the drive's link (lower first)."""

    STOP = 0  # the stop, the ramp-down on a lost link, their read-back of standstill
    KEEPER = 1  # the drive's watchdog refresh
    WEB = 2  # the web process's forwarded reads and writes


_urgency: contextvars.ContextVar[Urgency] = contextvars.ContextVar("drive_link_urgency", default=Urgency.WEB)


@contextlib.contextmanager
def urgency(level: Urgency) -> Iterator[None]:
    """Exchanges on the drive's link made inside the block (in this task) wait as ``level``."""
    token = _urgency.set(level)
    try:
        yield
    finally:
        _urgency.reset(token)


def set_task_urgency(level: Urgency) -> None:
    """The calling task's exchanges wait as ``level`` for the rest of its life (the keeper)."""
    _urgency.set(level)


class TurnLock:
    """A lock whose waiters are served most urgent first, then in the order they came."""

    def __init__(self) -> None:
        self._held = False
        self._waiting: list[tuple[int, int, asyncio.Future[None]]] = []
        self._seq = itertools.count()

    @property
    def held(self) -> bool:
        return self._held

    def waiting(self) -> int:
        """Waiters not yet served (cancelled ones excluded)."""
        return sum(1 for _, _, f in self._waiting if not f.done())

    @contextlib.asynccontextmanager
    async def turn(self, level: Urgency) -> AsyncIterator[None]:
        await self._acquire(level)
        try:
            yield
        finally:
            self._release()

    async def _acquire(self, level: Urgency) -> None:
        if not self._held and not self.waiting():
            self._held = True
            return
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        heapq.heappush(self._waiting, (int(level), next(self._seq), fut))
        try:
            await fut
        except asyncio.CancelledError:
            if fut.done() and not fut.cancelled():  # handed the turn, then cancelled: pass it on
                self._release()
            raise

    def _release(self) -> None:
        while self._waiting:
            _, _, fut = heapq.heappop(self._waiting)
            if not fut.done():
                fut.set_result(None)  # the turn passes directly: _held stays True
                return
        self._held = False


class OneAtATime:
    """A register transport carrying one exchange at a time, most urgent first (module docstring)."""

    def __init__(self, inner: RegisterTransport) -> None:
        self.inner = inner
        self.description = inner.description
        self.lock = TurnLock()

    @property
    def connected(self) -> bool:
        return bool(getattr(self.inner, "connected", False))

    async def open(self) -> None:
        await self.inner.open()

    async def read(self, address: int, count: int, what: str, function: int = 0x03) -> list[int]:
        async with self.lock.turn(_urgency.get()):
            return await self.inner.read(address, count, what, function)

    async def write(self, address: int, words: Sequence[int], what: str, *, retry: bool = True) -> None:
        async with self.lock.turn(_urgency.get()):
            await self.inner.write(address, words, what, retry=retry)

    async def close(self) -> None:
        await self.inner.close()
