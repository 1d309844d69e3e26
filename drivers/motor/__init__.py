"""Crank drive driver (Modbus TCP/RTU) for any drive described by a profile (``config/drives/``).

The names below load their modules at first use: the drive profile and the errors (a station's
configuration checks its profile with them) do not import pymodbus and the controller.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
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

# each name's module, imported at the name's first use
_MODULE_OF = {
    "MotorController": "drivers.motor.controller",
    "MotorStatus": "drivers.motor.controller",
    "MotorCommunicationError": "drivers.motor.errors",
    "MotorError": "drivers.motor.errors",
    "MotorExceptionReplyError": "drivers.motor.errors",
    "MotorFaultError": "drivers.motor.errors",
    "MotorLinkError": "drivers.motor.errors",
    "MotorProtocolError": "drivers.motor.errors",
    "MotorSafetyError": "drivers.motor.errors",
    "MotorStateError": "drivers.motor.errors",
    "MotorTimeoutError": "drivers.motor.errors",
    "MotorValueError": "drivers.motor.errors",
    "RegisterMapError": "drivers.motor.errors",
    "DriveProfile": "drivers.motor.profile",
    "load_profile": "drivers.motor.profile",
    "parse_profile": "drivers.motor.profile",
    "shipped_profiles": "drivers.motor.profile",
    "Register": "drivers.motor.registers",
    "LinkPolicy": "drivers.motor.transport",
    "ModbusTransport": "drivers.motor.transport",
    "RegisterTransport": "drivers.motor.transport",
    "transport_from_url": "drivers.motor.transport",
}

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


def __getattr__(name: str) -> Any:
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # looked up once
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
