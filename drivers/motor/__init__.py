"""Crank motor-controller driver (Modbus TCP/RTU); register map in ``config/motor_registers.yaml``."""

from drivers.motor.controller import MotorController, MotorStatus
from drivers.motor.errors import (
    MotorCommunicationError,
    MotorError,
    MotorExceptionReplyError,
    MotorFaultError,
    MotorLinkError,
    MotorProtocolError,
    MotorStateError,
    MotorTimeoutError,
    MotorValueError,
    RegisterMapError,
)
from drivers.motor.registers import Register, RegisterMap, load_register_map
from drivers.motor.transport import LinkPolicy, ModbusTransport, RegisterTransport, transport_from_url

__all__ = [
    "LinkPolicy",
    "ModbusTransport",
    "MotorCommunicationError",
    "MotorController",
    "MotorError",
    "MotorExceptionReplyError",
    "MotorFaultError",
    "MotorLinkError",
    "MotorProtocolError",
    "MotorStateError",
    "MotorStatus",
    "MotorTimeoutError",
    "MotorValueError",
    "Register",
    "RegisterMap",
    "RegisterMapError",
    "RegisterTransport",
    "load_register_map",
    "transport_from_url",
]
