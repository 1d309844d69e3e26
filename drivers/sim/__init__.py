"""Simulated twins of the rig's devices: a real Modbus server and a DAQ-bridge emulator on ptys."""

from drivers.sim.daq_emulator import DaqEmulator
from drivers.sim.daq_source import RigSource, SampleSource, SineSource
from drivers.sim.motor_inprocess import InProcessTransport
from drivers.sim.motor_model import MotorModel
from drivers.sim.motor_server import ModbusFaults, MotorEmulator
from drivers.sim.rig import SimRig, SimRigAddresses, SimRigProcess

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
