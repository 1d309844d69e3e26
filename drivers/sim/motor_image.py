"""Register image of the emulated motor controller: the device logic behind the Modbus server.

:class:`MotorRegisterImage` maps register reads/writes onto the :class:`MotorModel`.  It is used
by the pymodbus server (via its ``SimDevice`` action) and directly by the in-process backend, so
both speak the same device logic.  Errors are returned as Modbus exception codes.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence

from drivers.motor.registers import Register, RegisterMap
from drivers.sim.motor_model import MotorModel

log = logging.getLogger(__name__)

ILLEGAL_ADDRESS = 0x02
ILLEGAL_VALUE = 0x03
DEVICE_FAILURE = 0x04


class _Refused(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


class MotorRegisterImage:
    """Reads produce the live state; writes command the model.  Thread-safe through the model."""

    def __init__(self, regmap: RegisterMap, model: MotorModel) -> None:
        self.map = regmap
        self.model = model
        self._by_addr: dict[int, tuple[Register, int]] = {}
        for reg in regmap.registers.values():
            for i in range(reg.words):
                self._by_addr[reg.address + i] = (reg, i)
        self._stored: dict[str, float] = {"watchdog": 0.0}
        # called with (register name, value, time.monotonic()) for every register a write applied
        self.observers: list[Callable[[str, float, float], None]] = []

    def _values(self) -> dict[str, float]:
        s = self.model.snapshot()
        m = self.map
        status = {
            "enabled": s.enabled,
            "running": s.speed_hz != 0.0,
            "at_setpoint": s.enabled and s.speed_hz == s.setpoint_hz,
            "ramping": s.speed_hz != s.target_hz,
            "fault": s.fault_code != 0,
            "watchdog_expired": s.watchdog_expired,
            "estop_active": s.estop,
        }
        values = {
            "enable": float(s.enabled),
            "frequency_setpoint": s.setpoint_hz,
            "acceleration_ramp": s.ramp_hz_per_s,
            "watchdog": self._stored["watchdog"],
            "watchdog_timeout": s.watchdog_timeout_s,
            "emergency_stop": float(s.estop),
            "fault_reset": 0.0,
            "actual_speed": s.speed_hz,
            "crank_angle": self._wrapped_angle_deg(s.angle_rad),
            "status_word": float(m.encode_status({k: v for k, v in status.items() if k in m.status_bits})),
            "fault_code": float(s.fault_code),
            "revolution_count": float(math.floor(s.angle_rad / (2 * math.pi)) % (1 << 32)),
            "max_frequency": self.model.device.max_frequency_hz,
        }
        if "crank_angle" in m.registers and m["crank_angle"].unit == "rad":
            values["crank_angle"] = s.angle_rad % (2 * math.pi)
        return values

    def _wrapped_angle_deg(self, angle_rad: float) -> float:
        """Angle in [0, 360) deg that never rounds up to 360.00 in the register's resolution."""
        deg = math.degrees(angle_rad % (2 * math.pi))
        half_lsb = 0.5 * abs(self.map["crank_angle"].scale)
        return 0.0 if deg >= 360.0 - half_lsb else deg

    def _raw_words(self, reg: Register, value: float) -> list[int]:
        lo, hi = reg.raw_range()
        raw = min(max(round((value - reg.offset) / reg.scale), lo), hi)  # saturate like a drive would
        return reg.encode(raw * reg.scale + reg.offset)

    def read(self, address: int, count: int) -> list[int] | int:
        """Words ``address .. address+count-1`` or a Modbus exception code."""
        if count < 1 or any(a not in self._by_addr for a in range(address, address + count)):
            return ILLEGAL_ADDRESS
        values = self._values()
        out: list[int] = []
        for a in range(address, address + count):
            reg, i = self._by_addr[a]
            out.append(self._raw_words(reg, values.get(reg.name, 0.0))[i])
        return out

    def write(self, address: int, words: Sequence[int]) -> int | None:
        """Apply a write of whole registers, all or nothing; returns a Modbus exception code or None.

        Every value is checked against its register's declared range first (exception 03); then the
        registers are applied in address order inside one model transaction, so a write refused part
        way (e.g. exception 04) changes nothing.
        """
        end = address + len(words)
        regs: list[Register] = []
        a = address
        while a < end:
            entry = self._by_addr.get(a)
            if entry is None or entry[1] != 0 or not entry[0].writable or a + entry[0].words > end:
                return ILLEGAL_ADDRESS
            regs.append(entry[0])
            a += entry[0].words
        values = [(reg, reg.decode(words[reg.address - address: reg.address - address + reg.words]))
                  for reg in regs]
        for reg, value in values:
            if not reg.in_range(value):
                lo, hi = reg.valid_range()
                log.info("motor emulator: write %s=%s outside [%g, %g]: exception 3", reg.name, value, lo, hi)
                return ILLEGAL_VALUE
        stored = dict(self._stored)
        try:
            with self.model.atomic():
                for reg, value in values:
                    code = self._apply(reg.name, value)
                    if code is not None:
                        log.info("motor emulator: write %s=%s refused with exception %d", reg.name, value, code)
                        raise _Refused(code)
        except _Refused as refused:
            self._stored = stored
            return refused.code
        if self.observers:
            now = time.monotonic()
            for reg, value in values:
                for fn in self.observers:
                    fn(reg.name, value, now)
        return None

    def _apply(self, name: str, value: float) -> int | None:
        model = self.model
        try:
            if name == "enable":
                if value not in (0.0, 1.0):
                    return ILLEGAL_VALUE
                model.set_enable(value == 1.0)
            elif name == "frequency_setpoint":
                model.set_setpoint(value)
            elif name == "acceleration_ramp":
                model.set_ramp(value)
            elif name == "watchdog":
                self._stored["watchdog"] = value
                model.refresh_watchdog()
            elif name == "watchdog_timeout":
                model.set_watchdog_timeout(value)
            elif name == "emergency_stop":
                if value == 1.0:
                    model.emergency_stop()
                elif value != 0.0:
                    return ILLEGAL_VALUE
            elif name == "fault_reset":
                if value == 1.0:
                    model.reset_faults()
                elif value != 0.0:
                    return ILLEGAL_VALUE
            else:
                return ILLEGAL_ADDRESS
        except ValueError:
            return ILLEGAL_VALUE
        except PermissionError:
            return DEVICE_FAILURE
        return None
