"""Change notification: every waiter on a run (server-sent event streams) wakes on its next change.

Lives on the web side's event loop; the rig thread reports through ``loop.call_soon_threadsafe``."""

from __future__ import annotations

import asyncio
import contextlib
from collections import OrderedDict
from dataclasses import dataclass, field

MAX_TRACKED = 256  # runs whose change counters are kept (the newest changed; older waiters time out and re-read)


@dataclass
class _Change:
    version: int = 0
    event: asyncio.Event = field(default_factory=asyncio.Event)

    def bump(self) -> None:
        self.version += 1
        self.event.set()
        self.event = asyncio.Event()


class Changes:
    """A version counter per run; ``wait`` returns at the next change, a time-out or ``closing``."""

    def __init__(self, closing: asyncio.Event) -> None:
        self._changes: OrderedDict[str, _Change] = OrderedDict()
        self._closing = closing

    def _entry(self, run_id: str) -> _Change:
        ch = self._changes.get(run_id)
        if ch is None:
            ch = self._changes[run_id] = _Change()
            while len(self._changes) > MAX_TRACKED:
                self._changes.popitem(last=False)
        else:
            self._changes.move_to_end(run_id)
        return ch

    def changed(self, run_id: str) -> None:
        self._entry(run_id).bump()

    def bump_all(self) -> None:
        for ch in self._changes.values():
            ch.bump()

    def version(self, run_id: str) -> int:
        ch = self._changes.get(run_id)
        return 0 if ch is None else ch.version

    async def wait(self, run_id: str, since: int, timeout_s: float) -> int:
        ch = self._entry(run_id)
        if ch.version == since and not self._closing.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(ch.event.wait(), timeout_s)
        return self.version(run_id)

    def forget(self, run_id: str) -> None:
        """Drop a run's entry once it has ended and nobody waits on it (keeps memory flat)."""
        self._changes.pop(run_id, None)

    def __len__(self) -> int:
        return len(self._changes)
