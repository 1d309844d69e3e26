"""Connecting the run procedure to a rig: the real devices, or the emulators of the simulated rig.

Both backends give the same three things (motor driver, DAQ driver, radius actuator); the choice is
made here, at connect time, and the procedure never asks which one it has.  The simulated rig runs
the emulators in-process and the *real* drivers talk to them over Modbus TCP and a pseudo-terminal;
given a clock (``sim_clock``, e.g. a virtual one in tests) it runs without a wire instead: the real
drivers on in-process backends, everything keeping that clock's time.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from drivers.clock import REAL_CLOCK, Clock
from drivers.daq.bridge import DaqBridge
from drivers.daq.link import ByteLink, SerialLink
from drivers.motor.controller import MotorController
from drivers.motor.profile import DriveProfile, load_profile
from drivers.motor.transport import ModbusTransport, RegisterTransport, transport_from_url
from drivers.rig.params import RigPhysics
from station.config import StationConfig, to_rig_physics
from station.run.hardware import check_daq_hardware
from station.run.procedure import FixedRadius, Procedure, Progress, RadiusActuator, RunProcedure
from station.run.request import Plan
from station.run.stream import LocalStream, RecordingStream

if TYPE_CHECKING:
    from drivers.sim.rig import SimRig

log = logging.getLogger(__name__)


class RemoteRuns(Protocol):
    """Makes the remote form of a run's procedure (``rigproc/remoterun.RemoteProcedure``)."""

    def __call__(self, plan: Plan, rig: ConnectedRig, out_dir: Path, *, run_id: str,
                 on_progress: Callable[[Progress], None], disk_reserve: Path | None) -> RunProcedure: ...


def _mounted(physics: RigPhysics) -> None:
    """A real rig carries whatever is mounted on it: a plan changes nothing there."""


@dataclass
class ConnectedRig:
    """The procedure's view of a rig (see ``procedure.RigDevices``), whichever backend it has.

    ``load(plan)`` readies the rig for a run (the simulated rig then synthesises the plan's physics,
    e.g. its top mass; a real rig has what is mounted).  ``sim`` holds the simulated rig's emulators
    for tests' fault hooks (``rig.sim.motor.inject_fault(3)``); the station never reads it."""

    motor: MotorController
    daq: RecordingStream  # the DAQ stream into the run's recording
    radius: RadiusActuator
    description: str = ""
    clock: Clock = REAL_CLOCK
    simulated: bool = False
    on_load: Callable[[RigPhysics], None] = _mounted
    sim: SimRig | None = None
    release: Callable[[], Awaitable[None]] | None = None  # tells the rig process an acknowledged stop is over
    on_run: Callable[[str | None], Awaitable[None]] | None = None  # tells the rig process the run (its stop names it)
    remote: RemoteRuns | None = None  # the run's procedure carried out in the rig process (``procedure``)

    def procedure(self, plan: Plan, out_dir: Path, *, run_id: str, on_progress: Callable[[Progress], None],
                  on_disk_full: Callable[[], int] | None = None, disk_reserve: Path | None = None) -> RunProcedure:
        """The run's procedure on this rig: in this process, or its remote form in the rig process
        (``disk_reserve``: the file it frees there when the disk is full, as ``on_disk_full`` does here)."""
        if self.remote is not None:
            return self.remote(plan, self, out_dir, run_id=run_id, on_progress=on_progress, disk_reserve=disk_reserve)
        return Procedure(plan, self, out_dir, run_id=run_id, on_progress=on_progress, on_disk_full=on_disk_full)

    def load(self, plan: Plan) -> None:
        """Ready the rig for ``plan`` (before its procedure starts).  A real rig's configuration
        has no ``simulation`` section to take physics from: nothing is derived for it."""
        if self.on_load is not _mounted:
            self.on_load(to_rig_physics(plan.config))

    def health(self) -> dict[str, Any]:
        """State of each device link, for /health."""
        t = self.motor.transport
        return {"motor": {"connected": bool(getattr(t, "connected", False)),
                          "watchdog_error": str(self.motor.watchdog_error or "") or None,
                          "link_error": getattr(t, "error", None)},  # e.g. the rig process's end
                "daq": {"link_error": self.daq.link_error},
                "simulated": self.simulated}


async def connect_drivers(cfg: StationConfig, profile: DriveProfile, motor_transport: RegisterTransport,
                           open_daq: Callable[[], ByteLink],
                           clock: Clock = REAL_CLOCK) -> tuple[MotorController, LocalStream]:
    """Both drivers connected (the DAQ bridge's stream in this process, on ``clock``), and the
    configuration checked against what the DAQ bridge reports
    (:func:`~station.run.hardware.check_daq_hardware`); nothing is written to the drive here."""
    motor = MotorController(profile, clock=clock)
    await motor.connect(motor_transport)
    daq = DaqBridge()
    try:
        daq.connect(open_daq())  # stops a stream left running, drains, checks idle
        hw = daq.hardware or daq.read_hardware()
        check_daq_hardware(cfg, hw)
    except BaseException:
        daq.close()
        with contextlib.suppress(Exception):
            await motor.close()
        raise
    log.info("DAQ bridge: %s; %s, %d bits, channels %s, link %s", hw.identity, hw.adc, hw.adc_bits,
             ",".join(hw.channels), hw.link)
    return motor, LocalStream(daq, clock)


@contextlib.asynccontextmanager
async def connect(cfg: StationConfig, *, sim: bool, seed: int | None = None,
                  first_radius_m: float | None = None,
                  sim_clock: Clock | None = None) -> AsyncIterator[ConnectedRig]:
    """Connect to the rig (``sim``: start the emulators first); closes everything on exit.

    ``sim_clock``: run the simulated rig without a wire (in-process backends of the same drivers)
    on this clock, e.g. a :class:`drivers.sim.clock.VirtualClock`; without it the drivers talk to
    the emulators over Modbus TCP and a pseudo-terminal in real time.
    """
    if sim_clock is not None and not sim:
        raise ValueError("sim_clock is for the simulated rig (sim=True); a real rig keeps real time")
    rig: SimRig | None = None
    motor = daq = None
    clock: Clock = sim_clock or REAL_CLOCK
    profile = load_profile(cfg.rig.motor.profile)
    try:
        if sim:
            from drivers.sim.rig import SimRig  # the emulators (numpy's filters, scipy): only where they run

            physics = to_rig_physics(cfg)
            radius = first_radius_m or cfg.plan.steps[0].crank_radius_m
            s = cfg.simulation.seed if seed is None and cfg.simulation else (seed or 0)
            if sim_clock is not None:
                rig = SimRig(physics=physics, seed=s, crank_radius_m=radius, wire=False, clock=clock,
                             profile=profile, daq_link=cfg.devices.daq_link).start()
                motor, daq = await connect_drivers(cfg, profile, rig.motor_transport(), rig.daq_link, clock)
                desc = "simulated rig (in-process, no wire)"
            else:
                rig = SimRig(physics=physics, seed=s, crank_radius_m=radius, rtu=False, profile=profile,
                             daq_link=cfg.devices.daq_link).start()
                host, port = rig.addresses.modbus_tcp
                motor, daq = await connect_drivers(
                    cfg, profile, ModbusTransport.tcp(host, port, device_id=profile.transport.unit_id),
                    lambda: SerialLink(rig.addresses.daq, baudrate=cfg.devices.daq_baudrate,
                                       kind=cfg.devices.daq_link))
                desc = f"simulated rig (Modbus TCP {host}:{port}, DAQ {rig.addresses.daq})"
            actuator: RadiusActuator = rig.radius_actuator()
        else:
            dev = cfg.devices
            t = profile.transport
            transport = transport_from_url(dev.motor_url, device_id=dev.motor_device_id or t.unit_id,
                                           baudrate=t.baudrate, parity=t.parity, stopbits=t.stopbits,
                                           inter_frame_delay_s=t.inter_frame_delay_s)
            motor, daq = await connect_drivers(
                cfg, profile, transport, lambda: SerialLink(dev.daq_port, baudrate=dev.daq_baudrate, kind=dev.daq_link))
            actuator = FixedRadius(dev.crank_radius_m)
            desc = f"rig (motor {profile.name} at {dev.motor_url}, DAQ {dev.daq_port})"
        if rig is not None:
            yield ConnectedRig(motor, daq, actuator, desc, clock, simulated=True, on_load=rig.load_physics, sim=rig)
        else:
            yield ConnectedRig(motor, daq, actuator, desc, clock)
    finally:
        if motor is not None:
            with contextlib.suppress(Exception):
                await motor.close()
        if daq is not None:
            with contextlib.suppress(Exception):
                await _while_waiting(clock, daq.close)
        if rig is not None:
            rig.close()


async def _while_waiting(clock: Clock, fn: Callable[[], object]) -> None:
    """Run the blocking ``fn`` in a thread while this task waits on ``clock``, so that a virtual
    clock can move on for the threads ``fn`` waits for (e.g. a reader thread's last read)."""
    fut = asyncio.ensure_future(asyncio.to_thread(fn))
    while not fut.done():
        await clock.asleep(0.02)
    fut.result()
