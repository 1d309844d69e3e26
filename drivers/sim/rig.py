"""``SimRig``: the motor-controller emulator and the DAQ-bridge emulator sharing one motor state.

In-process (tests, ``station sim-rig``)::

    with SimRig(seed=1) as rig:
        rig.addresses.modbus_tcp        # ("127.0.0.1", port)
        rig.addresses.modbus_rtu        # /dev/pts/N  (Modbus RTU client side)
        rig.addresses.daq               # /dev/pts/M  (DAQ bridge serial port)
        rig.motor.inject_fault(3)       # MotorModel hooks; rig.modbus_faults, rig.daq for the rest

Without a wire (``SimRig(wire=False, clock=VirtualClock())``): no Modbus server and no pty; the
drivers connect through :meth:`SimRig.motor_transport` and :meth:`SimRig.daq_link`, and the motor
model and the DAQ emulator keep the given clock's time, so a run takes milliseconds in tests.

As a subprocess: ``python -m drivers.sim``, driven by :class:`drivers.sim.process.SimRigProcess`.
"""

from __future__ import annotations

import asyncio
import logging
import math
import socket
import threading
from collections.abc import Coroutine
from typing import Any, TypeVar

from drivers.clock import REAL_CLOCK, Clock
from drivers.daq.link import SocketLink
from drivers.motor.profile import DriveProfile, load_profile
from drivers.rig.params import RigPhysics
from drivers.rig.presets import paper_5kN_physics
from drivers.sim.daq_emulator import DaqEmulator
from drivers.sim.daq_inprocess import ClockedDaqLink
from drivers.sim.daq_source import RigSource, SampleSource
from drivers.sim.motor_image import MotorRegisterImage
from drivers.sim.motor_inprocess import InProcessTransport
from drivers.sim.motor_model import MotorModel
from drivers.sim.motor_server import ModbusFaults, MotorEmulator
from drivers.sim.process import SimRigAddresses
from drivers.sim.pty import Pty, open_pty

log = logging.getLogger(__name__)
T = TypeVar("T")


class SimRig:
    """Context manager starting both emulators; the Modbus servers run in a private event loop thread."""

    def __init__(self, *, physics: RigPhysics | None = None, seed: int = 0, crank_radius_m: float = 0.01,
                 profile: DriveProfile | None = None, modbus_port: int = 0, rtu: bool = True,
                 source: SampleSource | None = None, fifo_bytes: int = 1 << 20, wire: bool = True,
                 clock: Clock = REAL_CLOCK, rtu_local_echo: bool = False, daq_link: str = "uart",
                 daq_link_bytes_per_s: float = 1_000_000.0) -> None:
        """``profile``: the drive the motor emulator behaves as (default: the station's own controller);
        ``daq_link``: the link kind the bridge emulator reports (``uart`` or ``usb-cdc``, then with
        ``daq_link_bytes_per_s``, about what a full-speed USB CDC port sustains)."""
        self.map = profile or load_profile()  # the drive the motor emulator behaves as
        self.clock = clock
        self.built_s = clock.monotonic()  # the rig's age (the transducer's ageing) counts from here
        self.idle_days = 0.0  # days the rig stood idle beyond its clock's time (``let_days_pass``)
        self.wire = wire
        self.motor = MotorModel(self.map.device, clock=clock.monotonic)
        self.image = MotorRegisterImage(self.map, self.motor)
        self.source = source or RigSource(physics or paper_5kN_physics(), seed=seed,
                                          crank_radius_m=crank_radius_m)
        self._modbus = MotorEmulator(self.image, tcp_port=modbus_port, rtu=rtu, rtu_local_echo=rtu_local_echo)
        self._seed = seed
        self._fifo = fifo_bytes
        self._daq_kind = daq_link
        self._daq_bps = daq_link_bytes_per_s if daq_link == "usb-cdc" else None
        # the bridge reports the resolution its source's converter quantises at
        self._adc_bits = self.source.physics.adc.bits if isinstance(self.source, RigSource) else 16
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._pty: Pty | None = None
        self.daq: DaqEmulator
        self.addresses: SimRigAddresses

    @property
    def modbus_faults(self) -> ModbusFaults:
        """Reply drops and exception replies of the Modbus server (see :class:`ModbusFaults`)."""
        return self._modbus.faults

    def run(self, coro: Coroutine[Any, Any, T], timeout_s: float = 10.0) -> T:
        """Run a coroutine on the emulator loop (e.g. ``rig.run(rig.modbus.stop_tcp())``)."""
        assert self._loop is not None
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(timeout_s)

    @property
    def modbus(self) -> MotorEmulator:
        return self._modbus

    def start(self) -> SimRig:
        if not self.wire:
            if isinstance(self.source, RigSource):
                self.source.set_phase(self.motor.snapshot().angle_rad % (2 * math.pi))
            self.daq = DaqEmulator(None, self.source, self.motor.speed_hz, seed=self._seed,
                                   fifo_bytes=self._fifo, clock=self.clock, link=self._daq_kind,
                                   link_bytes_per_s=self._daq_bps, adc_bits=self._adc_bits).start()
            log.info("sim rig: in-process (no wire)")
            return self
        ready = threading.Event()

        def loop_main() -> None:
            self._loop = asyncio.new_event_loop()
            asyncio.set_event_loop(self._loop)
            ready.set()
            self._loop.run_forever()

        self._thread = threading.Thread(target=loop_main, name="sim-rig-modbus", daemon=True)
        self._thread.start()
        ready.wait()
        self.run(self._modbus.start())
        self._pty = open_pty()
        if isinstance(self.source, RigSource):
            self.source.set_phase(self.motor.snapshot().angle_rad % (2 * math.pi))
        self.daq = DaqEmulator(self._pty.master, self.source, self.motor.speed_hz, seed=self._seed,
                               fifo_bytes=self._fifo, on_close=self._pty.forget_master,
                               link=self._daq_kind, link_bytes_per_s=self._daq_bps,
                               adc_bits=self._adc_bits).start()
        assert self._modbus.tcp_address is not None
        self.addresses = SimRigAddresses(self._modbus.tcp_address, self._modbus.rtu_path, self._pty.path)
        log.info("sim rig: %s", self.addresses)
        return self

    def set_crank_radius(self, radius_m: float) -> None:
        """Change the crank radius (m) of the synthesised signals; only at standstill (RuntimeError)."""
        speed = self.motor.speed_hz()
        if speed != 0.0:
            raise RuntimeError(f"the crank radius can only change at standstill (crank at {speed:.2f} Hz)")
        if not isinstance(self.source, RigSource):
            raise RuntimeError("the crank radius needs the rig-physics source (RigSource)")
        self.source.set_crank_radius(radius_m)

    async def change_crank_radius(self, radius_m: float, timeout_s: float = 3.0) -> None:
        """Change the crank radius (m) as a motorised eccentric would: wait (up to ``timeout_s`` on
        the rig's clock) for true standstill of the emulated crank, then change it (RuntimeError
        naming the speed if the crank does not come to rest)."""
        deadline = self.clock.monotonic() + timeout_s
        while True:
            try:
                self.set_crank_radius(radius_m)
                return
            except RuntimeError as exc:
                if "standstill" not in str(exc) or self.clock.monotonic() > deadline:
                    raise RuntimeError(f"crank radius change refused: {exc}") from exc
            await self.clock.asleep(0.02)

    def age_days(self) -> float:
        """Days since the rig was built: its clock's time and the days it was let stand idle."""
        return (self.clock.monotonic() - self.built_s) / 86_400.0 + self.idle_days

    def let_days_pass(self, days: float) -> None:
        """The rig stands idle for ``days`` (e.g. until the next night's check run): the transducer
        ages by them (``effects.ageing``) while the emulators' clock is not moved, so nothing has to
        catch up with the time (a test's nights, a demonstration)."""
        if not days >= 0:
            raise ValueError(f"days cannot go backwards ({days})")
        self.idle_days += days

    def load_physics(self, physics: RigPhysics) -> None:
        """Synthesise the signals with other physics from now on (e.g. a run's top mass), aged to the
        rig's clock (``effects.ageing``: the transducer's slow drift between runs); the crank keeps
        turning where it is.  Only for the rig-physics source (RuntimeError otherwise)."""
        if not isinstance(self.source, RigSource):
            raise RuntimeError("other physics need the rig-physics source (RigSource)")
        self.source.load(physics.aged(self.age_days()))

    def radius_actuator(self) -> SimCrankRadius:
        """The crank-radius actuator of this rig, for the run procedure (``radius_m``, ``set_radius``)."""
        return SimCrankRadius(self)

    def motor_transport(self) -> InProcessTransport:
        """In-process backend of the motor driver on this rig's register image (no wire)."""
        return InProcessTransport(self.image)

    def daq_link(self) -> ClockedDaqLink:
        """In-process backend of the DAQ driver on this rig's emulator (``wire=False`` only)."""
        if self.wire:
            raise RuntimeError("this rig's DAQ emulator speaks over a pty: open rig.addresses.daq")
        return ClockedDaqLink(self.daq)

    def inprocess_daq(self) -> tuple[DaqEmulator, SocketLink]:
        """A second DAQ emulator on a socketpair (no pty) sharing the motor: (emulator, driver link)."""
        a, b = socket.socketpair()
        a.setblocking(False)
        src = self.source
        if isinstance(src, RigSource):
            src = RigSource(src.physics, seed=self._seed, crank_radius_m=src.crank_radius_m)
        emu = DaqEmulator(a.detach(), src, self.motor.speed_hz, seed=self._seed).start()
        return emu, SocketLink(b)

    def close(self) -> None:
        if getattr(self, "daq", None) is not None:
            self.daq.close()
        if self._pty is not None:
            self._pty.close()
            self._pty = None
        if self._loop is not None:
            self.run(self._modbus.stop())
            self._loop.call_soon_threadsafe(self._loop.stop)
            if self._thread is not None:
                self._thread.join(timeout=5.0)
            self._loop.close()
            self._loop = None

    def __enter__(self) -> SimRig:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


class SimCrankRadius:
    """The simulated rig's motorised crank radius: ``set_radius`` waits for standstill, then changes it."""

    def __init__(self, rig: SimRig) -> None:
        self._rig = rig
        src = rig.source
        self.radius_m = float(src.crank_radius_m) if isinstance(src, RigSource) else 0.0

    async def set_radius(self, radius_m: float) -> None:
        await self._rig.change_crank_radius(radius_m)
        self.radius_m = radius_m
