"""The emulated drives for the drive tests: a profile's drive in-process on a virtual clock, a short
calibration's configuration on a given drive profile, and the specification of a rig process built
in-process on such a drive (no channel, no stop port)."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from pathlib import Path

import yaml

from drivers.motor import MotorController
from drivers.motor.profile import DriveProfile
from drivers.sim.clock import VirtualClock
from drivers.sim.motor_image import MotorRegisterImage
from drivers.sim.motor_inprocess import InProcessTransport
from drivers.sim.motor_model import MotorModel
from station.rigproc.serve import Spec

ROOT = Path(__file__).resolve().parent.parent
RIG_SPEC = Spec(socket="", motor_url="modbus-tcp://127.0.0.1:1", device_id=None, profile=None, stop_host=None,
                stop_port=0, names=(), page_port=None, header_timeout_s=5.0, priority="normal", link_timeout_s=3.0)


def drive(profile: DriveProfile, body: Callable[[MotorController, MotorModel, MotorRegisterImage, VirtualClock],
                                                Awaitable[None]]) -> MotorRegisterImage:
    """Run ``body`` against the profile's emulated drive, in-process on a virtual clock."""
    clock = VirtualClock()
    model = MotorModel(profile.device, clock=clock.monotonic)
    image = MotorRegisterImage(profile, model)

    async def go() -> None:
        motor = MotorController(profile, clock=clock)
        await motor.connect(InProcessTransport(image))
        await body(motor, model, image, clock)
        await motor.close()

    asyncio.run(go())
    return image


def calibration_config(profile: str) -> dict:
    d = yaml.safe_load((ROOT / "config" / "sim-5kN.yaml").read_text())
    d["rig"]["motor"] = {"profile": profile}
    d["rig"]["crank_frequency_hz"] = {"min": 1.0, "max": 40.0}
    d["rig"]["acceleration_hz_per_s"] = 50.0
    d["plan"].update({"settle_s": 0.1, "record_s": 0.5})
    d["plan"]["steps"] = [{"crank_frequency_hz": 10.0, "crank_radius_m": 0.002},
                          {"crank_frequency_hz": 25.0, "crank_radius_m": 0.001}]
    return d
