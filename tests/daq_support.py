"""The DAQ bridge emulator for the driver tests: a source whose every sample can be checked, and the
emulator serving it on a real pseudo-terminal."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import numpy as np

from drivers.sim.daq_emulator import DaqEmulator
from drivers.sim.pty import open_pty


class CounterSource:
    """Displacement = running sample counter (mod 2^16), force = its negative: every sample is checkable."""

    def __init__(self) -> None:
        self.k = 0

    def configure(self, rate_hz: float, range_disp_V: float, range_force_V: float) -> None:
        return None

    def advance(self, n: int, f_end_hz: float) -> tuple[np.ndarray, np.ndarray]:
        d = (np.arange(self.k, self.k + n) % 65536).astype(np.uint16).view(np.int16)
        self.k += n
        return d, (-d.astype(np.int32)).astype(np.int16)


@contextlib.contextmanager
def emulator_on_pty(source: Any = None, crank_hz: float = 20.0, **emu: Any) -> Iterator[tuple[DaqEmulator, str]]:
    """A started :class:`DaqEmulator` of ``source`` (a :class:`CounterSource` by default) at a crank of
    ``crank_hz`` (Hz) on a new pseudo-terminal; yields (the emulator, the pty's path for the driver).
    ``emu``: the emulator's options (e.g. ``seed``, ``link``); closed on leaving."""
    pty = open_pty()
    e = DaqEmulator(pty.master, source or CounterSource(), lambda t: crank_hz, on_close=pty.forget_master,
                    **emu).start()
    try:
        yield e, pty.path
    finally:
        e.close()
        pty.close()
