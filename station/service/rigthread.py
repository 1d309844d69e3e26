"""The rig's own thread and event loop.

Everything that talks to the rig (the connection, the motor driver's watchdog keeper, the run
procedure or, with the daemon's rig, the following of it in the rig process; the acquisition has
threads of its own) runs on this loop, never on the web side's: a
large or slow request body, a flood of requests or a handler that blocks cannot delay a watchdog
refresh or a step of the procedure.  The web side hands work over with ``call``/``submit`` and
receives progress through ``loop.call_soon_threadsafe`` on its own loop.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import threading
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")


def close_loop(loop: asyncio.AbstractEventLoop) -> None:
    """After ``run_forever`` returned on a thread's own loop: cancel what is left, let it end, close."""
    pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
    for t in pending:
        t.cancel()
    if pending:
        loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
    loop.close()


class RigThread:
    """A daemon thread running an asyncio loop until ``stop``."""

    def __init__(self, name: str = "rig-control") -> None:
        self.name = name
        self.loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> RigThread:
        if self._thread is not None:
            return self
        ready = threading.Event()

        def main() -> None:
            loop = asyncio.new_event_loop()
            asyncio.set_event_loop(loop)
            self.loop = loop
            ready.set()
            try:
                loop.run_forever()
            finally:
                close_loop(loop)

        self._thread = threading.Thread(target=main, name=self.name, daemon=True)
        self._thread.start()
        ready.wait()
        return self

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def in_thread(self) -> bool:
        return self._thread is not None and threading.get_ident() == self._thread.ident

    def submit(self, coro: Coroutine[Any, Any, T]) -> concurrent.futures.Future[T]:
        """Schedule ``coro`` on the rig loop; the future's cancel() cancels it there."""
        if self.loop is None:
            coro.close()
            raise RuntimeError("the rig thread is not running")
        return asyncio.run_coroutine_threadsafe(coro, self.loop)

    async def call(self, coro: Coroutine[Any, Any, T]) -> T:
        """Run ``coro`` on the rig loop and await its result from another loop (or directly, when
        already on the rig loop)."""
        if self.in_thread():
            return await coro
        return await asyncio.wrap_future(self.submit(coro))

    def call_soon(self, fn: Callable[..., Any], *args: Any) -> None:
        """Call ``fn(*args)`` on the rig loop (thread-safe)."""
        if self.loop is None or self.loop.is_closed():
            return
        if self.in_thread():
            fn(*args)
        else:
            self.loop.call_soon_threadsafe(fn, *args)

    def stop(self, timeout_s: float = 10.0) -> None:
        loop, thread = self.loop, self._thread
        if loop is None or thread is None:
            return
        if not loop.is_closed():
            loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout_s)
        if thread.is_alive():
            log.error("the rig thread did not end within %.0f s", timeout_s)
        self._thread = None
        self.loop = None
