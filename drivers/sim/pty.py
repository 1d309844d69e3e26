"""Pseudo-terminal helpers for the emulators: raw pty pairs and a two-pty byte bridge.

A pty has a master fd (the emulator's end) and a slave path (``/dev/pts/N``) that a driver opens
with pyserial exactly as it would open ``/dev/ttyUSB0``.  :class:`PtyBridge` joins two ptys like
``socat pty pty`` so that two programs that both want a *path* (pymodbus' serial server and a
serial client) can talk.
"""

from __future__ import annotations

import contextlib
import logging
import os
import selectors
import threading
import time
import tty
from dataclasses import dataclass

log = logging.getLogger(__name__)


@dataclass
class Pty:
    """A raw-mode pty: ``master`` fd for the emulator, ``path`` of the slave for the driver.

    The slave fd is kept open so the master never sees EIO while no driver is attached.
    """

    master: int
    slave: int
    path: str

    def forget_master(self) -> None:
        """The master fd was closed by its owner (e.g. the DAQ emulator): do not close it again."""
        self.master = -1

    def close(self) -> None:
        for fd in (self.master, self.slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self.master = self.slave = -1


def open_pty() -> Pty:
    """A new raw (no echo, no line discipline) pty; the master fd is non-blocking."""
    master, slave = os.openpty()
    tty.setraw(slave)
    tty.setraw(master)
    os.set_blocking(master, False)
    return Pty(master, slave, os.ttyname(slave))


class PtyBridge:
    """Copies bytes both ways between the masters of two ptys in a daemon thread.

    ``echo_b``: whatever the program on ``b`` writes is also sent back to it (the local echo of an
    RS-485 half-duplex adapter that hears its own transmitter).  Like a USB adapter that packs what
    it received into one USB transfer, the echo is held until the answer from ``a`` comes (then both
    go in one write) or for at most ``echo_hold_s``.
    """

    def __init__(self, *, echo_b: bool = False, echo_hold_s: float = 0.05) -> None:
        self.a = open_pty()
        self.b = open_pty()
        self.echo_b = echo_b
        self.echo_hold_s = echo_hold_s
        self._echo = b""
        self._echo_since = 0.0
        self._wake_r, self._wake_w = os.pipe()
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="pty-bridge", daemon=True)

    def start(self) -> PtyBridge:
        self._thread.start()
        return self

    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self.a.master, selectors.EVENT_READ, self.b.master)
        sel.register(self.b.master, selectors.EVENT_READ, self.a.master)
        sel.register(self._wake_r, selectors.EVENT_READ, None)
        try:
            while not self._stop:
                events = sel.select(timeout=0.01 if self._echo else 0.5)
                if self._echo and time.monotonic() - self._echo_since > self.echo_hold_s:
                    self._write_all(self.b.master, self._echo)
                    self._echo = b""
                for key, _ in events:
                    if key.data is None:
                        return
                    try:
                        data = os.read(key.fd, 65536)
                    except BlockingIOError:
                        continue
                    except OSError as exc:
                        log.debug("pty bridge: read failed: %s", exc)
                        return
                    if self.echo_b and key.fd == self.b.master:
                        if not self._echo:
                            self._echo_since = time.monotonic()
                        self._echo += data
                    elif self._echo and key.fd == self.a.master:
                        data, self._echo = self._echo + data, b""
                    self._write_all(key.data, data)
        finally:
            sel.close()

    @staticmethod
    def _write_all(fd: int, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(fd, view)
                view = view[n:]
            except BlockingIOError:
                time.sleep(0.001)
            except OSError:
                return

    def close(self) -> None:
        self._stop = True
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self.a.close()
        self.b.close()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
