"""A virtual clock for the simulated rig: time jumps ahead whenever everything waiting on it waits.

Every thread or asyncio task that waits on the clock (``sleep``, ``asleep``, ``wait_for``) is a
*participant*.  A pacer thread moves time forward to the earliest wake-up of the waiting
participants, but only while **no** participant is awake (running between two waits): a woken
participant holds the clock until it waits again, so producers (the DAQ emulator's sample pacing)
and consumers (the acquisition, the procedure) keep step the way they would in real time, while the
idle gaps between events cost no wall-clock time.  A calibration run with seconds of ramps,
settling and records then takes milliseconds to a second.

A participant awake longer than ``hold_s`` of *real* time (blocked on something the clock does not
see, or starved of CPU) stops holding the clock until its next wait, so a forgotten participant
slows a test but never deadlocks it; :attr:`VirtualClock.released` counts those events.  While such
a participant is out, time moves no faster than real time, so it cannot miss its deadlines by more
than it would on the real clock.

Only in-process backends can run on it (the motor model through the in-process register image, the
DAQ emulator through :class:`~drivers.sim.daq_inprocess.ClockedDaqLink`); wire protocols (pymodbus
servers, ptys) keep the real clock.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field
from typing import Any

log = logging.getLogger(__name__)


@dataclass(eq=False)
class _Participant:
    alive: Callable[[], bool]
    wake: float | None = None                      # virtual wake-up time while waiting, else None
    predicate: Callable[[], bool] | None = None
    result: bool = False
    woke_real: float = field(default_factory=time.monotonic)
    released: bool = False                          # awake too long: not holding the clock
    future: asyncio.Future[None] | None = None
    loop: asyncio.AbstractEventLoop | None = None


class VirtualClock:
    """Virtual monotonic time (seconds, starting at ``start_s``) for in-process simulations.

    ``hold_s``: real seconds an awake participant may hold the clock (see the module docstring).
    ``advance(dt)`` moves time by hand (tests of a single component; no pacer needed).
    """

    def __init__(self, start_s: float = 1000.0, *, hold_s: float = 0.5) -> None:
        self._now = float(start_s)
        self.hold_s = hold_s
        self._cond = threading.Condition()
        self._parts: dict[object, _Participant] = {}
        self._pacer: threading.Thread | None = None
        self.advances = 0
        self.released = 0
        self._last_advance_real = time.monotonic()

    # ------------------------------------------------------------------ Clock protocol
    def monotonic(self) -> float:
        return self._now

    def sleep(self, seconds: float) -> None:
        self.wait_for(_never, seconds)

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        if predicate():
            return True
        if timeout_s <= 0:
            return False
        th = threading.current_thread()
        with self._cond:
            part = self._participant(th, th.is_alive)
            part.wake, part.predicate, part.result = self._now + timeout_s, predicate, False
            if predicate():  # changed between the first check and registering
                self._wake(part, True)
                return True
            self._ensure_pacer()
            self._cond.notify_all()
            while part.wake is not None:
                self._cond.wait()
            return part.result

    async def asleep(self, seconds: float) -> None:
        if seconds <= 0:
            await asyncio.sleep(0)
            return
        loop = asyncio.get_running_loop()
        task = asyncio.current_task()
        fut: asyncio.Future[None] = loop.create_future()
        with self._cond:
            part = self._participant(task, (lambda: not task.done()) if task is not None else (lambda: False))
            part.wake, part.predicate, part.future, part.loop = self._now + seconds, None, fut, loop
            self._ensure_pacer()
            self._cond.notify_all()
        try:
            await fut
        finally:
            with self._cond:
                if part.wake is not None:  # cancelled while waiting
                    part.wake, part.future = None, None
                    part.woke_real, part.released = time.monotonic(), False
                    self._cond.notify_all()

    def notify(self) -> None:
        with self._cond:
            for part in list(self._parts.values()):
                if part.wake is not None and part.predicate is not None and part.predicate():
                    self._wake(part, True)
            self._cond.notify_all()

    def hold(self) -> None:
        """Make the calling thread (or task) a participant that is awake now: time stands still
        until it waits on the clock (or ``hold_s`` of real time passed), e.g. while it starts the
        other participants."""
        task = None
        with contextlib.suppress(RuntimeError):
            task = asyncio.current_task()
        if task is not None:
            self._awake(task, lambda: not task.done())
        else:
            th = threading.current_thread()
            self._awake(th, th.is_alive)

    def start_task(self, coro: Coroutine[Any, Any, None], name: str) -> asyncio.Task[None]:
        """Start ``coro`` as a task, a participant awake from now: time stands still until it first
        waits on the clock (or ``hold_s`` of real time passed).  Without this, the caller's next
        wait could let time jump ahead before the new task ran at all (a watchdog keeper started
        just before the caller sleeps: the drive's watchdog expired in virtual time)."""
        task = asyncio.create_task(coro, name=name)
        self._awake(task, lambda: not task.done())
        return task

    def _awake(self, key: object, alive: Callable[[], bool]) -> None:
        """Register ``key`` (a task or a thread; ``alive`` tells when it is gone) as awake now."""
        with self._cond:
            part = self._participant(key, alive)
            part.wake, part.woke_real = None, time.monotonic()
            self._ensure_pacer()

    # ------------------------------------------------------------------ by hand
    def advance(self, seconds: float) -> None:
        """Move time forward by ``seconds`` and wake whoever is due (for single-component tests)."""
        if seconds < 0:
            raise ValueError(f"time cannot go backwards ({seconds} s)")
        with self._cond:
            self._now += seconds
            self._wake_due()

    # ------------------------------------------------------------------ internals
    def _participant(self, key: object, alive: Callable[[], bool]) -> _Participant:
        part = self._parts.get(key)
        if part is None:
            part = self._parts[key] = _Participant(alive)
        part.released = False
        return part

    def _wake(self, part: _Participant, result: bool) -> None:
        part.wake, part.result = None, result
        part.woke_real, part.released = time.monotonic(), False
        fut, loop = part.future, part.loop
        part.future = None
        if fut is not None and loop is not None:
            with contextlib.suppress(RuntimeError):  # loop already closed
                loop.call_soon_threadsafe(_resolve, fut)
        self._cond.notify_all()

    def _wake_due(self) -> None:
        for part in list(self._parts.values()):
            if part.wake is not None and part.wake <= self._now:
                self._wake(part, part.predicate() if part.predicate is not None else False)

    def _ensure_pacer(self) -> None:
        if self._pacer is None or not self._pacer.is_alive():
            self._pacer = threading.Thread(target=self._pace, name="virtual-clock", daemon=True)
            self._pacer.start()

    def _pace(self) -> None:
        idle_since = time.monotonic()
        with self._cond:
            while True:
                now_real = time.monotonic()
                for key, part in list(self._parts.items()):
                    if not part.alive():
                        del self._parts[key]
                if not self._parts:
                    if now_real - idle_since > 1.0:
                        self._pacer = None
                        return
                    self._cond.wait(0.05)
                    continue
                idle_since = now_real
                holding = [p for p in self._parts.values() if p.wake is None and not p.released]
                if holding:
                    oldest = min(p.woke_real for p in holding)
                    if now_real - oldest >= self.hold_s:
                        for p in holding:
                            if now_real - p.woke_real >= self.hold_s:
                                p.released = True
                                self.released += 1
                                log.debug("virtual clock: a participant held it %.2f s real; released",
                                          now_real - p.woke_real)
                        continue
                    self._cond.wait(min(0.05, self.hold_s - (now_real - oldest)))
                    continue
                waiting = [p.wake for p in self._parts.values() if p.wake is not None]
                if not waiting:
                    self._cond.wait(0.05)
                    continue
                t = min(waiting)
                if t > self._now and any(p.wake is None for p in self._parts.values()):
                    # someone is awake but released: no faster than real time until it waits again
                    ahead = (t - self._now) - (now_real - self._last_advance_real)
                    if ahead > 0:
                        self._cond.wait(min(0.05, ahead))
                        continue
                if t > self._now:
                    self._now = t
                    self.advances += 1
                    self._last_advance_real = now_real
                self._wake_due()


def _never() -> bool:
    return False


def _resolve(fut: asyncio.Future[Any]) -> None:
    if not fut.done():
        fut.set_result(None)
