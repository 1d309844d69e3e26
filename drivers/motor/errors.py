"""Typed errors of the motor-controller driver.  Every error names the register it concerns."""

from __future__ import annotations

EXCEPTION_NAMES: dict[int, str] = {
    0x01: "ILLEGAL FUNCTION",
    0x02: "ILLEGAL DATA ADDRESS",
    0x03: "ILLEGAL DATA VALUE",
    0x04: "SERVER DEVICE FAILURE",
    0x05: "ACKNOWLEDGE",
    0x06: "SERVER DEVICE BUSY",
    0x08: "MEMORY PARITY ERROR",
    0x0A: "GATEWAY PATH UNAVAILABLE",
    0x0B: "GATEWAY TARGET DEVICE FAILED TO RESPOND",
}


class RegisterMapError(ValueError):
    """The register-map YAML is malformed; the message says what was expected and what came."""


class MotorError(Exception):
    """Base class of motor-driver failures."""


class MotorValueError(MotorError, ValueError):
    """A value cannot be encoded into its register (out of the type's range or the device limits)."""


class MotorCommunicationError(MotorError):
    """A register access failed.  ``register`` names the register (or register block)."""

    def __init__(self, register: str, message: str) -> None:
        super().__init__(f"register {register!r}: {message}")
        self.register = register


class MotorTimeoutError(MotorCommunicationError):
    """No (valid) reply within the time-out, after all retries."""


class MotorLinkError(MotorCommunicationError):
    """The link is lost and could not be re-established within the reconnect budget."""


class MotorExceptionReplyError(MotorCommunicationError):
    """The controller answered with a Modbus exception reply (function code | 0x80)."""

    def __init__(self, register: str, function_code: int, exception_code: int) -> None:
        name = EXCEPTION_NAMES.get(exception_code, "unknown exception")
        super().__init__(
            register,
            f"Modbus exception reply to function 0x{function_code:02X}: "
            f"code 0x{exception_code:02X} ({name})",
        )
        self.function_code = function_code
        self.exception_code = exception_code


class MotorProtocolError(MotorCommunicationError):
    """A reply arrived but does not match the request (wrong length or function)."""


class MotorFaultError(MotorError):
    """The controller reports a latched fault (e.g. its watchdog expired)."""

    def __init__(self, fault_code: int, fault_name: str) -> None:
        super().__init__(f"motor controller fault {fault_code} ({fault_name})")
        self.fault_code = fault_code
        self.fault_name = fault_name


class MotorStateError(MotorError):
    """The controller is not in the state a command needs (e.g. turning when standstill is required)."""


class MotorSafetyError(MotorStateError):
    """A safety setting of the drive (its communication-loss stop, command source, stop method, the
    frequency its scaling rests on, ...) does not hold its required value after arming: the station
    refuses to enable the drive.  ``parameter`` is the drive's name of it (e.g. ``P9.04``)."""

    def __init__(self, profile: str, parameter: str, register: str, required: str, found: str, remedy: str) -> None:
        super().__init__(f"drive profile {profile!r}: {parameter} (register {register!r}) must be {required}, "
                         f"{found}; {remedy} -- the station does not enable the drive")
        self.parameter = parameter
        self.register = register
