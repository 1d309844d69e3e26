"""In-process backend of the DAQ driver: a byte link straight into a :class:`DaqEmulator`, no wire.

The emulator has no thread here: what the driver writes is handled at once (replies are ready to
read), and each read produces the frames due by the emulator's clock.  With a virtual clock
(:class:`drivers.sim.clock.VirtualClock`) the stream runs as fast as the driver consumes it, in
step with the emulated motor; the driver and everything above it is the real code.
"""

from __future__ import annotations

import threading

from drivers.daq.link import DaqLinkError
from drivers.sim.daq_emulator import DaqEmulator


class ClockedDaqLink:
    """A :class:`~drivers.daq.link.ByteLink` to an emulator created with ``fd=None``."""

    def __init__(self, emulator: DaqEmulator) -> None:
        if emulator.fd >= 0:
            raise ValueError("ClockedDaqLink drives an emulator without a port (DaqEmulator(fd=None, ...))")
        self.emulator = emulator
        self.description = "in-process DAQ emulator"
        self._lock = threading.Lock()

    def _take(self, max_bytes: int) -> bytes:
        with self._lock:
            if self.emulator.port_closed:
                raise DaqLinkError(f"{self.description}: closed by the bridge")
            return self.emulator.pull(max_bytes)

    def read(self, max_bytes: int, timeout_s: float) -> bytes:
        data = self._take(max_bytes)
        if data:
            return data
        self.emulator.clock.wait_for(self.emulator.has_output, timeout_s)
        return self._take(max_bytes)

    def write(self, data: bytes) -> None:
        with self._lock:
            if self.emulator.port_closed:
                raise DaqLinkError(f"{self.description}: write failed: port closed")
            self.emulator.feed(data)
        self.emulator.clock.notify()

    def close(self) -> None:
        self.emulator.close_port()
