"""Connecting the run procedure to a rig: the real devices, or the emulators of the simulated rig.

Both backends give the same three things (motor driver, DAQ driver, radius actuator); the choice is
made here, at connect time, and the procedure never asks which one it has.  The simulated rig runs
the emulators in-process and the *real* drivers talk to them over Modbus TCP and a pseudo-terminal.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

from drivers.daq.bridge import DaqBridge
from drivers.daq.link import SerialLink
from drivers.motor.controller import MotorController
from drivers.motor.transport import ModbusTransport, transport_from_url
from drivers.sim.rig import SimRig
from station.config import StationConfig, to_rig_physics
from station.run.procedure import FixedRadius, RadiusActuator, RunFailure

log = logging.getLogger(__name__)


@dataclass
class ConnectedRig:
    """The procedure's view of a rig (see ``procedure.RigLink``); ``sim`` is set on the simulated one."""

    motor: MotorController
    daq: DaqBridge
    radius: RadiusActuator
    sim: SimRig | None = None
    description: str = ""

    def health(self) -> dict[str, Any]:
        """State of each device link, for /health."""
        return {"motor": {"connected": bool(getattr(self.motor.transport, "connected", False)),
                          "watchdog_error": str(self.motor.watchdog_error or "") or None},
                "daq": {"link_error": str(self.daq.link_error or "") or None},
                "simulated": self.sim is not None}


class SimRadius:
    """The simulated rig's crank radius, changed at standstill like a motorised eccentric."""

    def __init__(self, rig: SimRig, radius_m: float) -> None:
        self._rig = rig
        self.radius_m = radius_m

    async def set_radius(self, radius_m: float, timeout_s: float = 3.0) -> None:
        """Wait (up to ``timeout_s``) for true standstill of the emulated crank, then change it."""
        deadline = asyncio.get_running_loop().time() + timeout_s
        while True:
            try:
                if abs(self._rig.motor.speed_hz()) > 0:
                    raise RuntimeError(f"crank at {self._rig.motor.speed_hz():g} Hz")
                self._rig.source.set_crank_radius(radius_m)  # type: ignore[attr-defined]
                break
            except RuntimeError as exc:
                if asyncio.get_running_loop().time() > deadline:
                    raise RunFailure(f"crank radius change refused: {exc}") from exc
                await asyncio.sleep(0.02)
        self.radius_m = radius_m


async def _connect_drivers(motor_transport: ModbusTransport, daq_port: str, baudrate: int) -> tuple[
        MotorController, DaqBridge]:
    motor = MotorController()
    await motor.connect(motor_transport)
    daq = DaqBridge()
    daq.connect(SerialLink(daq_port, baudrate=baudrate))
    ident = daq.identify()
    log.info("DAQ bridge: %s", ident)
    return motor, daq


@contextlib.asynccontextmanager
async def connect(cfg: StationConfig, *, sim: bool, seed: int | None = None,
                  first_radius_m: float | None = None) -> AsyncIterator[ConnectedRig]:
    """Connect to the rig (``sim``: start the emulators first); closes everything on exit."""
    rig: SimRig | None = None
    motor = daq = None
    try:
        if sim:
            physics = to_rig_physics(cfg)
            radius = first_radius_m or cfg.plan.steps[0].crank_radius_m
            s = cfg.simulation.seed if seed is None and cfg.simulation else (seed or 0)
            rig = SimRig(physics=physics, seed=s, crank_radius_m=radius, rtu=False).start()
            host, port = rig.addresses.modbus_tcp
            motor, daq = await _connect_drivers(ModbusTransport.tcp(host, port), rig.addresses.daq,
                                                cfg.devices.daq_baudrate)
            actuator: RadiusActuator = SimRadius(rig, radius)
            desc = f"simulated rig (Modbus TCP {host}:{port}, DAQ {rig.addresses.daq})"
        else:
            dev = cfg.devices
            transport = transport_from_url(dev.motor_url, device_id=dev.motor_device_id)
            motor, daq = await _connect_drivers(transport, dev.daq_port, dev.daq_baudrate)
            actuator = FixedRadius(dev.crank_radius_m)
            desc = f"rig (motor {dev.motor_url}, DAQ {dev.daq_port})"
        yield ConnectedRig(motor, daq, actuator, rig, desc)
    finally:
        if motor is not None:
            with contextlib.suppress(Exception):
                await motor.close()
        if daq is not None:
            with contextlib.suppress(Exception):
                daq.close()
        if rig is not None:
            rig.close()
