"""The clock a device, an emulator or the run procedure keeps time with (seconds, monotonic).

Real backends use :data:`REAL_CLOCK` (``time.monotonic``, ``time.sleep``, ``asyncio.sleep``).  The
simulated rig's in-process backends can run on a :class:`drivers.sim.clock.VirtualClock` instead,
so that a calibration run's ramps, settling, records and time-outs take milliseconds in tests.
Code that waits never asks which clock it has: it calls ``sleep``/``asleep``/``wait_for``.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable, Coroutine
from typing import Any, Protocol


class Clock(Protocol):
    """Monotonic time in seconds and the ways to wait on it."""

    def monotonic(self) -> float:
        """Now, in seconds (arbitrary origin)."""
        ...

    def sleep(self, seconds: float) -> None:
        """Block the calling thread for ``seconds`` of this clock's time."""
        ...

    async def asleep(self, seconds: float) -> None:
        """Suspend the calling task for ``seconds`` of this clock's time."""
        ...

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Block until ``predicate()`` is true (re-checked on :meth:`notify`) or ``timeout_s`` passed;
        returns the predicate's last value.  The predicate must be cheap and must not block."""
        ...

    def notify(self) -> None:
        """Something a :meth:`wait_for` predicate looks at has changed."""
        ...

    def start_task(self, coro: Coroutine[Any, Any, None], name: str) -> asyncio.Task[None]:
        """Start ``coro`` as a task of the running event loop, counted as awake from now until it
        first waits on this clock (a task that keeps something alive on a timer, e.g. the drive's
        watchdog, must not have the time it keeps run past before its first step)."""
        ...


class RealClock:
    """Wall-clock time: ``time.monotonic`` and real sleeps."""

    def __init__(self) -> None:
        self._cond = threading.Condition()

    def monotonic(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        time.sleep(max(0.0, seconds))

    async def asleep(self, seconds: float) -> None:
        await asyncio.sleep(max(0.0, seconds))

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        with self._cond:
            return self._cond.wait_for(predicate, max(0.0, timeout_s))

    def notify(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def start_task(self, coro: Coroutine[Any, Any, None], name: str) -> asyncio.Task[None]:
        return asyncio.create_task(coro, name=name)


REAL_CLOCK = RealClock()
"""The one real clock (its :meth:`RealClock.notify` wakes every ``wait_for`` on it)."""
