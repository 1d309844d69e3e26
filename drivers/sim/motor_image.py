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
NO_REPLY = -1  # the drive does not answer (it reboots)
_HISTORY = 16  # command-register writes kept for matching sequences
# the order in which sequences of the same length are tried: a stop is never taken for something else
_MATCH_ORDER = ("stop", "quick_stop", "fault_reset", "enable", "run")


class _Refused(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


class MotorRegisterImage:
    """Reads produce the live state; writes command the model.  Thread-safe through the model.

    ``writes`` counts the accepted writes per register (an EEPROM-backed register's wear),
    ``write_requests`` every write that arrived, answered or not (a command sent twice shows here)."""

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
        self._triggers = self._command_triggers()
        self.writes: Counter[str] = Counter()
        self.write_requests: Counter[str] = Counter()  # every write that arrived, answered or not
        self.commands_seen: list[str] = []
        # a drive with a ``run`` command is switched on by ``enable`` and follows the set point on ``run``
        self._two_stage = "run" in profile.commands.sequences
        self.switched_on = False
        # called with (register name, value, time.monotonic()) for every register a write applied
        self.observers: list[Callable[[str, float, float], None]] = []
        self.locked: set[str] = set()  # test hook: registers whose writes the drive answers but does not keep
        self._reboot_until = -math.inf  # model time until which the drive reboots (answers nothing)
        self._silent = False  # the write being applied gets no reply (the drive started rebooting)
        self.reboots = 0
        # a drive out of the box: the documented factory settings of its safety parameters and time-out
        for setting in profile.safety:
            if setting.default is not None:
                self._stored[setting.register] = setting.default
        if profile.watchdog.drive_default_s is not None:
            model.play_drive_defaults(profile.watchdog.drive_default_s)
        self._apply_settings()

    def _command_triggers(self) -> dict[str, tuple[str, int]]:
        """For a drive with one register per command (``model: registers``): the word each command
        acts on, the last (register, value) of its sequence that no other sequence writes (the GS2's
        EF = 1 stops it whatever follows); a command without one is matched as a whole sequence."""
        cmds = self.profile.commands
        if cmds.kind != "registers":
            return {}
        pairs = {c: [(s.register, s.value) for s in seq if s.register != self.profile.setpoint]
                 for c, seq in cmds.sequences.items()}
        out = {}
        for c, mine in pairs.items():
            others = {pair for o, theirs in pairs.items() if o != c for pair in theirs}
            unique = [pair for pair in mine if pair not in others]
            if unique:
                out[c] = unique[-1]
        return out

    # ------------------------------------------------------------------------------ the drive's settings
    def _holds(self, role_prefix: str) -> bool:
        """Whether every safety setting of the role(s) holds its required value in the drive."""
        return all(s.holds(self._stored.get(s.register, math.nan), self.profile[s.register].scale)
                   for s in self.profile.safety if s.role.startswith(role_prefix))

    def _apply_settings(self) -> None:
        """The drive acts on its settings: its watchdog stops the crank only while communication-loss
        detection and its action are set to stop."""
        self.model.set_watchdog_active(self._holds("comm_loss_"))

    def set_panel(self, register: str, value: float) -> None:
        """Test hook: a setting made on the drive's panel (any register, read-only ones too)."""
        self._stored[register] = float(value)
        self._apply_settings()

    def _max_frequency_hz(self) -> float:
        """The drive's maximum frequency (its own setting where the profile reads it, e.g. FH)."""
        p = self.profile
        return self._stored.get(p.max_frequency, p.device.max_frequency_hz) if p.max_frequency else \
            p.device.max_frequency_hz

    def _rebooting(self) -> bool:
        return self.model.snapshot().time_s < self._reboot_until

    def _reboot(self) -> None:
        """The drive restarts: no reply for ``reset_reboot_s``, its RAM (command word, set point) cleared."""
        p = self.profile
        self.reboots += 1
        self._reboot_until = self.model.snapshot().time_s + max(p.commands.reset_reboot_s, 0.5)
        self._silent = True
        self.model.set_enable(False)
        self.model.set_setpoint(max(0.0, p.device.min_frequency_hz))
        for name in self._command_regs:
            if not p[name].eeprom and name != p.setpoint:
                self._stored[name] = 0.0
        self._history.clear()
        self.switched_on = False

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
            ramp = s.ramp_hz_per_s if p.ramp.form == "rate" else self._max_frequency_hz() / s.ramp_hz_per_s
            values.update(dict.fromkeys(p.ramp.registers, ramp))
        if p.max_frequency:
            values[p.max_frequency] = self._max_frequency_hz()
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
        wd = self.profile.watchdog
        if wd.refresh is None and wd.rewrite is None:
            self.model.refresh_watchdog()  # every valid request refreshes this drive's watchdog

    def read(self, address: int, count: int, function: int = 0x03) -> list[int] | int:
        """Words ``address .. address+count-1`` or a Modbus exception code (03: more words than the drive
        reads at once; 02: an address outside the profile or of the other register kind)."""
        if count > self.profile.transport.max_registers_per_read:
            return ILLEGAL_VALUE  # the quantity is checked before the addresses (Modbus spec)
        if count < 1 or any(a not in self._by_addr or self._by_addr[a][0].read_function != function
                            for a in range(address, address + count)):
            return ILLEGAL_ADDRESS
        if self._rebooting():
            return NO_REPLY
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
        self.write_requests.update(reg.name for reg in regs)
        if self._rebooting():
            return NO_REPLY
        self._any_request()
        chunks = [(reg, words[reg.address - address: reg.address - address + reg.words]) for reg in regs]
        for reg, chunk in chunks:
            value = reg.decode(chunk)
            if not reg.in_range(value):
                lo, hi = reg.valid_range()
                log.info("motor emulator: write %s=%s outside [%g, %g]: exception 3", reg.name, value, lo, hi)
                return ILLEGAL_VALUE
        saved = (dict(self._stored), list(self._history), list(self.commands_seen), self.switched_on,
                 self._reboot_until, self.reboots)
        try:
            with self.model.atomic():
                for reg, chunk in chunks:
                    code = self._apply(reg, reg.decode(chunk), reg.decode_raw(chunk))
                    if code is not None:
                        log.info("motor emulator: write %s=%s refused with exception %d", reg.name,
                                 reg.decode(chunk), code)
                        raise _Refused(code)
        except _Refused as refused:
            (self._stored, self._history, self.commands_seen, self.switched_on, self._reboot_until,
             self.reboots) = saved
            self._silent = False
            return refused.code
        self.writes.update(reg.name for reg, _ in chunks)
        if self.observers:
            now = time.monotonic()
            for reg, chunk in chunks:
                for fn in self.observers:
                    fn(reg.name, reg.decode(chunk), now)
        if self._silent:
            self._silent = False
            return NO_REPLY
        return None

    def _matched_command(self) -> str | None:
        """The longest command sequence the latest command-register writes complete (with its holds)."""
        best: tuple[int, str] | None = None
        now_hist = self._history
        for command in _MATCH_ORDER:
            if command not in self.profile.commands.sequences:
                continue
            # the set point is no command register: a sequence's set-point steps are not in the history
            steps = tuple(s for s in self.profile.commands.sequences[command] if s.register != self.profile.setpoint)
            trigger = self._triggers.get(command)
            if trigger is not None:  # one register per command: the drive acts on that word alone
                if (now_hist[-1][0], now_hist[-1][1]) == trigger and (best is None or len(steps) > best[0]):
                    best = (len(steps), command)
                continue
            n = len(steps)
            if n == 0:
                continue
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
        rewrite_refresh = p.watchdog.rewrite is not None and (
            name in (p.setpoint, p.watchdog.rewrite) or name in self._command_regs)
        try:
            if rewrite_refresh:
                model.refresh_watchdog()  # a drive that counts received process data (the V20's F72)
            if name in self.locked:
                log.info("motor emulator: write %s=%s answered but not kept (locked)", name, value)
            elif name == p.setpoint:
                if self._holds("setpoint_source"):
                    model.set_setpoint(value)
                else:
                    self._stored[name] = value  # the drive follows another set-point source
            elif p.ramp is not None and name in p.ramp.registers:
                if p.ramp.form == "rate":
                    model.set_ramp(value)
                elif value <= 0:
                    return ILLEGAL_VALUE
                else:
                    model.set_ramp(self._max_frequency_hz() / value)
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
                if any(s.register == name for s in p.safety):
                    self._apply_settings()
        except ValueError:
            return ILLEGAL_VALUE
        except PermissionError:
            return DEVICE_FAILURE
        return None

    def _command(self, command: str) -> None:
        model = self.model
        cmds = self.profile.commands
        if command in ("enable", "run") and not self._holds("command_source"):
            return  # the drive takes its run command from another source (terminals, panel)
        if command == "quick_stop" and not cmds.repeat_quick_stop and model.snapshot().estop:
            self._reboot()  # told again while its quick stop is latched, this drive restarts
            return
        if command == "fault_reset" and cmds.reset_reboot_s > 0:
            model.reset_faults()  # refused while the crank turns (exception 04): no reboot then
            self._reboot()
            return
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
            if cmds.kind == "registers" and self._run_held():
                model.set_enable(True)  # its run register still says run: the drive starts again

    def _run_held(self) -> bool:
        """A drive with one register per command whose run register(s) still hold the enable value."""
        seq = [s for s in self.profile.commands.sequences["enable"] if s.register != self.profile.setpoint]
        if any(self.profile[s.register].reads_flag is not None for s in seq):
            return False  # a command register that reads back the drive's state holds no level of its own
        return bool(seq) and all(self._stored.get(s.register) == self.profile[s.register].decode(
            self.profile[s.register].words_of_raw(s.value)) for s in seq)
