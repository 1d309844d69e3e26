"""In-process backend of the motor driver: calls the emulator's register image directly.

For fast unit tests of code above the driver; it shares the device logic with the Modbus
emulator but skips the wire.  Exception codes become the same typed errors as over Modbus;
:meth:`InProcessTransport.cut` makes every access fail with ``MotorLinkError`` as a lost link would
(the emulated controller keeps running: its watchdog stops the motor).
"""

from __future__ import annotations

from collections.abc import Sequence

from drivers.motor.errors import MotorExceptionReplyError, MotorLinkError, MotorTimeoutError
from drivers.sim.motor_image import NO_REPLY, MotorRegisterImage


class InProcessTransport:
    """A :class:`~drivers.motor.transport.RegisterTransport` over a :class:`MotorRegisterImage`."""

    def __init__(self, image: MotorRegisterImage) -> None:
        self.image = image
        self.description = "in-process motor emulator"
        self.link_up = True

    @property
    def connected(self) -> bool:
        """False after :meth:`cut` (as a Modbus transport reports a lost connection)."""
        return self.link_up

    def cut(self) -> None:
        """Fault injection: the link is gone (every read and write raises ``MotorLinkError``)."""
        self.link_up = False

    def _check_link(self, what: str) -> None:
        if not self.link_up:
            raise MotorLinkError(what, "in-process link cut (fault injection)")

    async def open(self) -> None:
        return None

    async def read(self, address: int, count: int, what: str, function: int = 0x03) -> list[int]:
        self._check_link(what)
        result = self.image.read(address, count, function)
        if result == NO_REPLY:
            raise MotorTimeoutError(what, "no reply (the emulated drive reboots)")
        if isinstance(result, int):
            raise MotorExceptionReplyError(what, function, result)
        return result

    async def write(self, address: int, words: Sequence[int], what: str, *, retry: bool = True) -> None:
        """Sent once whatever ``retry`` says: nothing is lost in-process."""
        self._check_link(what)
        code = self.image.write(address, list(words))
        if code == NO_REPLY:
            raise MotorTimeoutError(what, "no reply (the emulated drive reboots)")
        if code is not None:
            raise MotorExceptionReplyError(what, 0x06 if len(words) == 1 else 0x10, code)

    async def close(self) -> None:
        return None
