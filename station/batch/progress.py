"""A dependency-free progress bar on stderr: redrawn in place on a terminal, one line per tenth of
the work otherwise (so that a journal gets a few lines, not hundreds)."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class ProgressBar:
    """``update(n)`` after each finished job, ``close()`` at the end."""

    def __init__(self, total: int, *, label: str = "recordings", stream: TextIO | None = None,
                 width: int = 30) -> None:
        self.total, self.label, self.width = max(total, 0), label, width
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.done = 0
        self._t0 = time.monotonic()
        self._last_draw = 0.0
        self._last_tenth = -1
        self._draw(force=True)

    def _line(self) -> str:
        frac = self.done / self.total if self.total else 1.0
        fill = int(self.width * frac)
        el = time.monotonic() - self._t0
        eta = f", {el * (1 - frac) / frac:.0f} s left" if 0 < frac < 1 else ""
        return (f"[{'#' * fill}{'.' * (self.width - fill)}] {self.done}/{self.total} {self.label} "
                f"({100 * frac:.0f} %, {el:.1f} s{eta})")

    def _draw(self, force: bool = False) -> None:
        now = time.monotonic()
        if self.tty:
            if force or now - self._last_draw >= 0.1 or self.done == self.total:
                self.stream.write("\r" + self._line())
                self.stream.flush()
                self._last_draw = now
            return
        tenth = int(10 * self.done / self.total) if self.total else 10
        if tenth != self._last_tenth:
            self.stream.write(self._line() + "\n")
            self.stream.flush()
            self._last_tenth = tenth

    def update(self, n: int = 1) -> None:
        self.done = min(self.total, self.done + n)
        self._draw()

    def close(self) -> None:
        if self.tty:
            self._draw(force=True)
            self.stream.write("\n")
            self.stream.flush()
