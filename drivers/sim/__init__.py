"""Simulated twins of the rig's devices: a real Modbus server and a DAQ-bridge emulator on ptys.

The names below load with their module on first use (``from drivers.sim import SimRig``): a
process that only starts the emulators in another one (:class:`SimRigProcess`) imports none of
the synthesis (numpy's filters, scipy, numba).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from drivers.sim.daq_emulator import DaqEmulator
    from drivers.sim.daq_source import RigSource, SampleSource, SineSource
    from drivers.sim.motor_inprocess import InProcessTransport
    from drivers.sim.motor_model import MotorModel
    from drivers.sim.motor_server import ModbusFaults, MotorEmulator
    from drivers.sim.process import SimRigAddresses, SimRigProcess
    from drivers.sim.rig import SimRig

_MODULE = {
    "DaqEmulator": "daq_emulator",
    "InProcessTransport": "motor_inprocess",
    "ModbusFaults": "motor_server",
    "MotorEmulator": "motor_server",
    "MotorModel": "motor_model",
    "RigSource": "daq_source",
    "SampleSource": "daq_source",
    "SimRig": "rig",
    "SimRigAddresses": "process",
    "SimRigProcess": "process",
    "SineSource": "daq_source",
}

__all__ = [
    "DaqEmulator",
    "InProcessTransport",
    "ModbusFaults",
    "MotorEmulator",
    "MotorModel",
    "RigSource",
    "SampleSource",
    "SimRig",
    "SimRigAddresses",
    "SimRigProcess",
    "SineSource",
]


def __getattr__(name: str) -> Any:
    if name not in _MODULE:
        raise AttributeError(f"module 'drivers.sim' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"drivers.sim.{_MODULE[name]}"), name)
    globals()[name] = value
    return value
