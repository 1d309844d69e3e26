"""Crank drive driver (Modbus TCP/RTU) for any drive described by a profile (``config/drives/``)."""

from drivers.motor.controller import MotorController, MotorStatus
from drivers.motor.errors import (
    MotorCommunicationError,
    MotorError,
    MotorExceptionReplyError,
    MotorFaultError,
    MotorLinkError,
    MotorProtocolError,
    MotorSafetyError,
    MotorStateError,
    MotorTimeoutError,
    MotorValueError,
    RegisterMapError,
)
from drivers.motor.profile import DriveProfile, load_profile, parse_profile, shipped_profiles
from drivers.motor.registers import Register
from drivers.motor.transport import LinkPolicy, ModbusTransport, RegisterTransport, transport_from_url

__all__ = [
    "DriveProfile",
    "LinkPolicy",
    "ModbusTransport",
    "MotorCommunicationError",
    "MotorController",
    "MotorError",
    "MotorExceptionReplyError",
    "MotorFaultError",
    "MotorLinkError",
    "MotorProtocolError",
    "MotorSafetyError",
    "MotorStateError",
    "MotorStatus",
    "MotorTimeoutError",
    "MotorValueError",
    "Register",
    "RegisterMapError",
    "RegisterTransport",
    "load_profile",
    "parse_profile",
    "shipped_profiles",
    "transport_from_url",
]
