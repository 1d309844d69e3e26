"""Register image of an emulated drive: any drive profile's registers on top of one :class:`MotorModel`.

:class:`MotorRegisterImage` makes the model look, register by register, like the drive a profile
describes: the set point, speed, ramp, watchdog and angle registers read and write the model in the
profile's scaling; the status word is composed from the model's state through the profile's flag
table; the fault code is the profile's code for the model's fault; and writes to command registers
are matched against the profile's command sequences (a control-word state machine, or one register
per command), with their hold times, before the model is commanded.  Other registers keep what was
written.  Where the profile says every request refreshes the watchdog, every request does.  It is used
by the pymodbus server (via its ``SimDevice`` action) and directly by the in-process backend, so both
speak the same device logic.  Errors are returned as Modbus exception codes.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Sequence

from drivers.motor.profile import FAULT_KINDS, DriveProfile
from drivers.motor.registers import Register
from drivers.sim.motor_model import FAULT_ESTOP, MotorModel

log = logging.getLogger(__name__)

ILLEGAL_ADDRESS = 0x02
ILLEGAL_VALUE = 0x03
DEVICE_FAILURE = 0x04
_HISTORY = 16  # command-register writes kept for matching sequences
# the order in which sequences of the same length are tried: a stop is never taken for something else
_MATCH_ORDER = ("stop", "quick_stop", "fault_reset", "enable", "run")


class _Refused(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


class MotorRegisterImage:
    """Reads produce the live state; writes command the model.  Thread-safe through the model.

    ``writes`` counts the accepted writes per register (an EEPROM-backed register's wear)."""

    def __init__(self, profile: DriveProfile, model: MotorModel) -> None:
        self.map = profile
        self.profile = profile
        self.model = model
        self._by_addr: dict[int, tuple[Register, int]] = {}
        for reg in profile.registers.values():
            for i in range(reg.words):
                self._by_addr[reg.address + i] = (reg, i)
        self._stored: dict[str, float] = {}
        self._history: list[tuple[str, int, float]] = []  # (register, raw value, time) of command writes
        self._command_regs = profile.commands.registers
        self.writes: Counter[str] = Counter()
        self.commands_seen: list[str] = []
        # a drive with a ``run`` command is switched on by ``enable`` and follows the set point on ``run``
        self._two_stage = "run" in profile.commands.sequences
        self.switched_on = False
        # called with (register name, value, time.monotonic()) for every register a write applied
        self.observers: list[Callable[[str, float, float], None]] = []

    # ------------------------------------------------------------------------------ reads
    def _fault_code(self, model_code: int) -> int:
        """The profile's code for the model's fault (0: none, or a quick stop the drive gives no code)."""
        if model_code == 0:
            return 0
        kind = FAULT_KINDS.get(model_code, "")
        if kind in self.profile.faults.kinds:
            return self.profile.faults.kinds[kind]
        if model_code == FAULT_ESTOP:
            return 0  # the drive shows a quick stop in its status word only
        return next((c for c in self.profile.faults.codes if c != 0), 0)  # 0: shown by the status word only

    def _values(self) -> dict[str, float]:
        s = self.model.snapshot()
        p = self.profile
        code = self._fault_code(s.fault_code)
        fault = s.fault_code != 0 and not (s.fault_code == FAULT_ESTOP and code == 0)
        truths = {
            "ready": not fault and not s.enabled and not s.estop,
            "enabled": s.enabled,
            "running": s.speed_hz != 0.0,
            "at_setpoint": s.enabled and s.speed_hz == s.setpoint_hz,
            "fault": fault,
            "estop": s.estop,
            "ramping": s.speed_hz != s.target_hz,
            "watchdog_expired": s.watchdog_expired,
            "switched_on": self.switched_on and not s.enabled and not fault and not s.estop,
        }
        values = dict(self._stored)
        values[p.setpoint] = s.setpoint_hz
        values[p.speed] = s.speed_hz
        values[p.status.register] = float(p.status.encode({k: truths.get(k, False) for k in p.status.flags}))
        values[p.watchdog.register] = s.watchdog_timeout_s
        if p.faults.register:
            values[p.faults.register] = float(code)
        if p.ramp is not None:
            ramp = s.ramp_hz_per_s if p.ramp.form == "rate" else p.device.max_frequency_hz / s.ramp_hz_per_s
            values.update(dict.fromkeys(p.ramp.registers, ramp))
        if p.max_frequency:
            values[p.max_frequency] = p.device.max_frequency_hz
        if p.angle:
            unit_deg = p[p.angle].unit == "deg"
            values[p.angle] = self._wrapped_angle_deg(s.angle_rad) if unit_deg else s.angle_rad % (2 * math.pi)
        for reg in p.registers.values():
            if reg.reads_flag is not None:
                values[reg.name] = float(truths.get(reg.reads_flag, False))
        if p.revolutions:
            values[p.revolutions] = float(math.floor(s.angle_rad / (2 * math.pi)) % (1 << 32))
        return values

    def _wrapped_angle_deg(self, angle_rad: float) -> float:
        """Angle in [0, 360) deg that never rounds up to 360.00 in the register's resolution."""
        deg = math.degrees(angle_rad % (2 * math.pi))
        assert self.profile.angle is not None
        half_lsb = 0.5 * abs(self.profile[self.profile.angle].scale)
        return 0.0 if deg >= 360.0 - half_lsb else deg

    def _raw_words(self, reg: Register, value: float) -> list[int]:
        lo, hi = reg.raw_range()
        raw = min(max(round((value - reg.offset) / reg.scale), lo), hi)  # saturate like a drive would
        return reg.words_of_raw(raw)

    def _any_request(self) -> None:
        if self.profile.watchdog.refresh is None:
            self.model.refresh_watchdog()  # every valid request refreshes this drive's watchdog

    def read(self, address: int, count: int, function: int = 0x03) -> list[int] | int:
        """Words ``address .. address+count-1`` or a Modbus exception code (03: more words than the drive
        reads at once; 02: an address outside the profile or of the other register kind)."""
        if count > self.profile.transport.max_registers_per_read:
            return ILLEGAL_VALUE  # the quantity is checked before the addresses (Modbus spec)
        if count < 1 or any(a not in self._by_addr or self._by_addr[a][0].read_function != function
                            for a in range(address, address + count)):
            return ILLEGAL_ADDRESS
        self._any_request()
        values = self._values()
        out: list[int] = []
        for a in range(address, address + count):
            reg, i = self._by_addr[a]
            out.append(self._raw_words(reg, values.get(reg.name, 0.0))[i])
        return out

    # ------------------------------------------------------------------------------ writes
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
        self._any_request()
        chunks = [(reg, words[reg.address - address: reg.address - address + reg.words]) for reg in regs]
        for reg, chunk in chunks:
            value = reg.decode(chunk)
            if not reg.in_range(value):
                lo, hi = reg.valid_range()
                log.info("motor emulator: write %s=%s outside [%g, %g]: exception 3", reg.name, value, lo, hi)
                return ILLEGAL_VALUE
        saved = (dict(self._stored), list(self._history), list(self.commands_seen), self.switched_on)
        try:
            with self.model.atomic():
                for reg, chunk in chunks:
                    code = self._apply(reg, reg.decode(chunk), reg.decode_raw(chunk))
                    if code is not None:
                        log.info("motor emulator: write %s=%s refused with exception %d", reg.name,
                                 reg.decode(chunk), code)
                        raise _Refused(code)
        except _Refused as refused:
            self._stored, self._history, self.commands_seen, self.switched_on = saved
            return refused.code
        self.writes.update(reg.name for reg, _ in chunks)
        if self.observers:
            now = time.monotonic()
            for reg, chunk in chunks:
                for fn in self.observers:
                    fn(reg.name, reg.decode(chunk), now)
        return None

    def _matched_command(self) -> str | None:
        """The longest command sequence the latest command-register writes complete (with its holds)."""
        best: tuple[int, str] | None = None
        now_hist = self._history
        for command in _MATCH_ORDER:
            if command not in self.profile.commands.sequences:
                continue
            steps = self.profile.commands.sequences[command]
            n = len(steps)
            if n > len(now_hist):
                continue
            tail = now_hist[-n:]
            if any((s.register, s.value) != (h[0], h[1]) for s, h in zip(steps, tail, strict=True)):
                continue
            if any(tail[i + 1][2] - tail[i][2] < steps[i].hold_s - 1e-9 for i in range(n - 1)):
                continue  # a step not held long enough is not seen by the drive
            if best is None or n > best[0]:
                best = (n, command)
        return None if best is None else best[1]

    def _apply(self, reg: Register, value: float, raw: int) -> int | None:
        p, model = self.profile, self.model
        name = reg.name
        try:
            if name == p.setpoint:
                model.set_setpoint(value)
            elif p.ramp is not None and name in p.ramp.registers:
                if p.ramp.form == "rate":
                    model.set_ramp(value)
                elif value <= 0:
                    return ILLEGAL_VALUE
                else:
                    model.set_ramp(p.device.max_frequency_hz / value)
            elif name == p.watchdog.register:
                model.set_watchdog_timeout(value)
            elif name == p.watchdog.refresh:
                self._stored[name] = value
                model.refresh_watchdog()
            elif name in self._command_regs:
                self._stored[name] = value
                self._history = [*self._history[-_HISTORY + 1:], (name, raw, model.snapshot().time_s)]
                command = self._matched_command()
                if command is not None:
                    self.commands_seen.append(command)
                    self._command(command)
            else:
                self._stored[name] = value
        except ValueError:
            return ILLEGAL_VALUE
        except PermissionError:
            return DEVICE_FAILURE
        return None

    def _command(self, command: str) -> None:
        model = self.model
        if command == "enable" and self._two_stage:
            if model.snapshot().fault_code:
                raise PermissionError("a fault is latched: reset it first")
            self.switched_on = True  # switched on; it follows the set point on "run"
        elif command in ("enable", "run"):
            if command == "run" and not self.switched_on:
                return  # not switched on: the drive ignores "run" (CiA 402: no transition)
            model.set_enable(True)
        elif command == "stop":
            model.set_enable(False)  # "disable operation": still switched on
        elif command == "quick_stop":
            self.switched_on = False
            model.emergency_stop()
        else:
            self.switched_on = False
            model.reset_faults()
