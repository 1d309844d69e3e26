"""Drive profiles: one YAML file describes a drive completely (``docs/drive-profiles.md``).

A profile gives the transport (RTU/TCP, character format, unit id, registers per read, inter-frame
delay, function codes), every register (:mod:`drivers.motor.registers`), which register plays which
part (set point, actual speed, status, fault code, ramp, crank angle), the command model (sequences of
register writes for enable, stop, quick stop and fault reset, each step with its hold time: a
control-word state machine, or one register per command), the status-bit table mapped onto the
station's canonical flags, the fault-code table and the communication watchdog.  The driver
(:class:`~drivers.motor.controller.MotorController`) and the emulator (``drivers.sim``) read the same
profile; nothing else declares an address.  Profiles ship in ``config/drives/`` (chosen by name) or
come from any path.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import yaml
from sinecal_config import config_file

from drivers.motor.errors import RegisterMapError
from drivers.motor.registers import Register, expect, is_number, parse_registers

DEFAULT_PROFILE = "sinecal-crank"
PROFILE_DIR = "drives"

# the station's canonical status flags; a profile maps its status bits onto these (and may add its own)
CANONICAL_FLAGS = ("ready", "enabled", "running", "at_setpoint", "fault", "estop")
# the station's fault kinds (the emulator's model latches these codes); a profile says which of its
# codes stands for each, where the drive has one
FAULT_KINDS = {1: "watchdog_expired", 2: "emergency_stop", 3: "overcurrent", 4: "overtemperature",
               5: "encoder_fault"}
# reported when the drive shows a state but gives no code for it (outside any 16-bit code)
# the station refreshes a drive's watchdog every 0.2 s while the crank may turn: a profile's time-out
# leaves room for two missed refreshes
MIN_WATCHDOG_TIMEOUT_S = 0.5
PSEUDO_ESTOP = 0x1_0000
PSEUDO_FAULT = 0x1_0001
COMMANDS = ("enable", "stop", "quick_stop", "fault_reset")
# optional: where a drive is first switched on (``enable``) and then told to follow the set point
# (``run``: CiA 402's "enable operation"), the station's enable is both sequences in turn
OPTIONAL_COMMANDS = ("run",)
RAMP_FORMS = ("rate", "time_to_max")
# what a safety setting stands for (the emulator plays each by its role): communication-loss detection
# and its action (the drive's watchdog stops the crank only while every such setting holds its value),
# the command and set-point sources (the drive follows bus commands only while they hold theirs), the
# stop method and ramps, and what the set point's scaling rests on (reference and maximum frequency,
# the upper limit)
SAFETY_ROLES = ("comm_loss_detection", "comm_loss_action", "command_source", "setpoint_source", "stop_method",
                "stop_ramp", "reference_frequency", "max_frequency", "upper_limit")


@dataclass(frozen=True)
class DeviceDefaults:
    """Drive-wide settings (SI units: Hz, Hz/s, s).  The frequency and ramp limits come from the
    ranges of the set-point and ramp registers (declared there, once)."""

    max_frequency_hz: float = 100.0
    min_frequency_hz: float = 0.0
    default_ramp_hz_per_s: float = 5.0
    max_ramp_hz_per_s: float = 100.0
    min_ramp_hz_per_s: float = 0.0  # the slowest ramp the ramp register(s) take (0: any positive one)
    stop_deceleration_hz_per_s: float = 50.0
    default_watchdog_timeout_s: float = 1.0
    reference_frequency_hz: float | None = None  # 100 % of a normalised set point (e.g. SINAMICS P2000)


_DEVICE_KEYS = {"default_ramp_hz_per_s", "stop_deceleration_hz_per_s", "reference_frequency_hz"}


@dataclass(frozen=True)
class TransportSpec:
    """How the drive talks: ``kind`` rtu|tcp (the default of a station that gives no URL scheme),
    RTU character format, unit id, Modbus function codes it answers, the longest read it accepts and
    the pause it needs between two frames (s)."""

    kind: str = "tcp"
    baudrate: int = 19200
    parity: str = "E"
    stopbits: int = 1
    unit_id: int = 1
    functions: tuple[int, ...] = (0x03, 0x06, 0x10)
    max_registers_per_read: int = 125
    inter_frame_delay_s: float = 0.0
    # registers whose write may be sent again after a time-out (idempotent: the same value twice is
    # the value once); every other write, a command word above all, goes out once
    retry_writes: tuple[str, ...] = ()


@dataclass(frozen=True)
class FlagSpec:
    """A flag is set when ``(word & mask) == value`` for any of ``alternatives``."""

    alternatives: tuple[tuple[int, int], ...]

    def test(self, word: int) -> bool:
        return any(word & m == v for m, v in self.alternatives)

    def apply(self, word: int, on: bool) -> int:
        """``word`` with this flag shown as ``on`` (the first alternative), or as off where that is one
        definite bit pattern (a single bit: cleared, or set when active low)."""
        mask, value = self.alternatives[0]
        if on:
            return (word & ~mask) | value
        if len(self.alternatives) == 1 and mask and mask & (mask - 1) == 0:
            return (word & ~mask) | (mask ^ value)
        return word


@dataclass(frozen=True)
class StatusTable:
    """The status word and its flags; ``idle_word``: the word with no flag set (bits a drive keeps set)."""

    register: str
    flags: Mapping[str, FlagSpec]
    idle_word: int = 0

    def decode(self, word: int) -> dict[str, bool]:
        return {name: spec.test(word) for name, spec in self.flags.items()}

    def encode(self, flags: Mapping[str, bool]) -> int:
        """{flag: on} -> status word, flags applied in the table's order; unknown names are an error."""
        word = self.idle_word
        for name in flags:
            if name not in self.flags:
                raise KeyError(f"unknown status flag {name!r} (have: {', '.join(self.flags)})")
        for name, spec in self.flags.items():
            if name in flags:
                word = spec.apply(word, bool(flags[name]))
        return word


@dataclass(frozen=True)
class FaultTable:
    """The fault-code register (None: the drive shows a fault only as a status flag), its codes and
    which code stands for which of the station's fault kinds (:data:`FAULT_KINDS`)."""

    register: str | None
    codes: Mapping[int, str]
    kinds: Mapping[str, int]

    def name(self, code: int) -> str:
        if code == PSEUDO_ESTOP:
            return "emergency_stop"
        if code == PSEUDO_FAULT:
            return "fault (the drive reports no code)"
        return self.codes.get(code, f"unknown_fault_{code}")


@dataclass(frozen=True)
class CommandStep:
    """Write raw ``value`` to ``register`` and keep it at least ``hold_s`` before the next step;
    ``verify``: read the register back after the sequence (it must hold ``value``)."""

    register: str
    value: int
    hold_s: float = 0.0
    verify: bool = False


@dataclass(frozen=True)
class CommandModel:
    """``kind``: ``control_word`` (one register, a state machine driven by word sequences) or
    ``registers`` (one register per command); ``sequences``: :data:`COMMANDS` (and, where the drive
    has it, ``run``) -> steps."""

    kind: str
    sequences: Mapping[str, tuple[CommandStep, ...]]
    reset_reboot_s: float = 0.0  # the fault reset reboots the drive for this long (s; 0: it does not)
    repeat_quick_stop: bool = True  # False: a second quick stop while one is latched is not sent

    @property
    def registers(self) -> set[str]:
        return {s.register for steps in self.sequences.values() for s in steps}


@dataclass(frozen=True)
class RampSpec:
    """The ramp parameter(s): ``rate`` (Hz/s) or ``time_to_max`` (s from 0 to the maximum frequency)."""

    registers: tuple[str, ...]
    form: str


@dataclass(frozen=True)
class WatchdogSpec:
    """The drive's communication watchdog: the parameter holding its time-out, the time-out the
    station sets (s, never 0: a profile whose watchdog is off is refused), the drive's smallest
    time-out, and how it is refreshed: a write to ``refresh`` (a rolling counter), a rewrite of the
    last value of ``rewrite`` (a drive that counts only received process data, e.g. the V20's F72),
    or neither when every valid request refreshes it (the driver then reads the status word)."""

    register: str
    timeout_s: float
    min_s: float
    refresh: str | None
    rewrite: str | None = None  # refreshed by rewriting this register's last value (process data)
    drive_default_s: float | None = None  # the drive's factory time-out (0: off); the emulator starts so
    parameter: str = ""  # the drive's name of the time-out parameter (F803, P9.05, P2014), for messages


@dataclass(frozen=True)
class SafetySetting:
    """A setting the drive must hold before the station enables it (``docs/drive-profiles.md``).

    ``register`` (its memory, RAM or EEPROM, is the register's), ``parameter`` (the drive's own name,
    e.g. ``P9.04``), ``role`` (one of :data:`SAFETY_ROLES`: what it stands for), ``how``: ``set``
    (the station writes ``value`` once when the drive holds another, then reads it back) or ``check``
    (read only: set on the panel at commissioning); the required value: ``value``, or a range
    ``min``..``max`` (checked only); ``meaning``: what the required value means, for the messages;
    ``default``: the drive's factory setting (the emulator starts with it; None: not documented)."""

    register: str
    parameter: str
    role: str
    how: str
    value: float | None = None
    min: float | None = None
    max: float | None = None
    meaning: str = ""
    default: float | None = None

    def holds(self, value: float, resolution: float = 0.0) -> bool:
        """Whether a read-back ``value`` satisfies the requirement (to half a register step)."""
        tol = 0.5 * abs(resolution)
        if self.value is not None:
            return abs(value - self.value) <= tol
        return ((self.min is None or value >= self.min - tol)
                and (self.max is None or value <= self.max + tol))

    def required(self) -> str:
        """The requirement for people, e.g. ``1 (enable)`` or ``at least 50``."""
        if self.value is not None:
            req = f"{self.value:g}"
        elif self.max is None:
            req = f"at least {self.min:g}"
        elif self.min is None:
            req = f"at most {self.max:g}"
        else:
            req = f"{self.min:g}..{self.max:g}"
        return f"{req} ({self.meaning})" if self.meaning else req


@dataclass(frozen=True)
class DriveProfile:
    """A drive as the station sees it (see the module docstring); frozen, validated at load."""

    name: str
    description: str
    sources: tuple[str, ...]
    transport: TransportSpec
    registers: Mapping[str, Register]
    device: DeviceDefaults
    setpoint: str
    speed: str
    status: StatusTable
    faults: FaultTable
    commands: CommandModel
    watchdog: WatchdogSpec
    ramp: RampSpec | None = None
    angle: str | None = None
    revolutions: str | None = None
    max_frequency: str | None = None
    path: str = ""
    extra_flags: tuple[str, ...] = field(default=())
    text: str = ""  # the YAML it was loaded from (stored with each recording)
    safety: tuple[SafetySetting, ...] = ()  # armed and read back before the first enable

    def __getitem__(self, name: str) -> Register:
        try:
            return self.registers[name]
        except KeyError:
            raise KeyError(f"no register {name!r} in profile {self.name!r} (have: "
                           f"{', '.join(self.registers)})") from None

    def blocks(self, names: Sequence[str]) -> list[tuple[int, int, int, list[str]]]:
        """Read requests covering ``names``: (function, first address, word count, names) of runs of
        registers read with the same function whose gaps are other registers of the profile (read
        along), within the drive's longest read."""
        regs = sorted((self[n] for n in dict.fromkeys(names)), key=lambda r: (r.read_function, r.address))
        mapped = {(r.read_function, r.address + i) for r in self.registers.values() for i in range(r.words)}
        out: list[tuple[int, int, int, list[str]]] = []
        limit = self.transport.max_registers_per_read
        for r in regs:
            if out:
                fc, start, count, members = out[-1]
                end = start + count
                gap_mapped = all((fc, a) in mapped for a in range(end, r.address))
                if fc == r.read_function and r.address >= end and gap_mapped and r.address + r.words - start <= limit:
                    out[-1] = (fc, start, r.address + r.words - start, [*members, r.name])
                    continue
            out.append((r.read_function, r.address, r.words, [r.name]))
        return out

    def span(self, names: Sequence[str]) -> tuple[int, int]:
        """(first address, word count) of the contiguous block covering ``names``."""
        regs = [self[n] for n in names]
        start = min(r.address for r in regs)
        return start, max(r.address + r.words for r in regs) - start

    def decode_status(self, word: int) -> dict[str, bool]:
        return self.status.decode(word)

    def encode_status(self, flags: Mapping[str, bool]) -> int:
        return self.status.encode(flags)

    def fault_name(self, code: int) -> str:
        return self.faults.name(code)

    def fault_code(self, name: str) -> int:
        for code, n in self.faults.codes.items():
            if n == name:
                return code
        raise KeyError(f"unknown fault {name!r} (have: {', '.join(self.faults.codes.values())})")


# ------------------------------------------------------------------------------------------ parsing
def _int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _transport(doc: Any, src: str) -> TransportSpec:
    doc = {} if doc is None else doc
    expect(isinstance(doc, dict), f"{src}: transport", "a mapping", doc)
    known = {f.name for f in fields(TransportSpec)}
    extra = sorted(str(k) for k in set(doc) - known)
    expect(not extra, f"{src}: transport", f"only keys {sorted(known)}", extra)
    kw: dict[str, Any] = {k: (tuple(v) if k in ("functions", "retry_writes") and isinstance(v, list) else v)
                          for k, v in doc.items()}
    t = TransportSpec(**kw)
    expect(t.kind in ("rtu", "tcp"), f"{src}: transport.kind", "'rtu' or 'tcp'", t.kind)
    expect(_int(t.baudrate) and t.baudrate > 0, f"{src}: transport.baudrate", "a positive integer", t.baudrate)
    expect(t.parity in ("E", "O", "N"), f"{src}: transport.parity", "'E', 'O' or 'N'", t.parity)
    expect(t.stopbits in (1, 2), f"{src}: transport.stopbits", "1 or 2", t.stopbits)
    expect(_int(t.unit_id) and 1 <= t.unit_id <= 247, f"{src}: transport.unit_id", "1..247", t.unit_id)
    expect(isinstance(t.functions, tuple) and all(_int(f) for f in t.functions)
           and set(t.functions) <= {0x03, 0x04, 0x06, 0x10} and 0x03 in t.functions
           and 0x06 in t.functions, f"{src}: transport.functions", "a list of 3, 4, 6, 16 with 3 and 6",
           t.functions)
    expect(_int(t.max_registers_per_read) and 1 <= t.max_registers_per_read <= 125,
           f"{src}: transport.max_registers_per_read", "1..125", t.max_registers_per_read)
    expect(is_number(t.inter_frame_delay_s) and 0 <= t.inter_frame_delay_s <= 1.0,
           f"{src}: transport.inter_frame_delay_s", "0..1 s", t.inter_frame_delay_s)
    return t


def _flag(spec: Any, where: str) -> FlagSpec:
    if isinstance(spec, dict) and "any" in spec:
        expect(set(spec) == {"any"} and isinstance(spec["any"], list) and bool(spec["any"]), where,
               "{any: [<flag>, ...]}", spec)
        return FlagSpec(tuple(alt for s in spec["any"] for alt in _flag(s, where).alternatives))
    expect(isinstance(spec, dict), where, "{bit: n} (active_low: true), {mask: m, value: v} or {any: [...]}",
           spec)
    if "bit" in spec:
        expect(set(spec) <= {"bit", "active_low"}, where, "only bit and active_low", sorted(map(str, spec)))
        bit = spec["bit"]
        expect(_int(bit) and 0 <= bit <= 15, f"{where}.bit", "0..15", bit)
        low = spec.get("active_low", False)
        expect(isinstance(low, bool), f"{where}.active_low", "true or false", low)
        return FlagSpec(((1 << bit, 0 if low else 1 << bit),))
    expect(set(spec) == {"mask", "value"}, where, "{mask: m, value: v}", sorted(map(str, spec)))
    m, v = spec["mask"], spec["value"]
    expect(_int(m) and 0 < m <= 0xFFFF and _int(v) and v & ~m == 0, where,
           "a 16-bit mask and a value within it", (m, v))
    return FlagSpec(((m, v),))


def _steps(doc: Any, where: str, default_register: str | None, regs: Mapping[str, Register],
           hold_s: float) -> tuple[CommandStep, ...]:
    expect(isinstance(doc, list) and bool(doc), where, "a non-empty list of steps", doc)
    out = []
    for i, step in enumerate(doc):
        w = f"{where}[{i}]"
        if _int(step):
            step = {"value": step}
        expect(isinstance(step, dict) and set(step) <= {"register", "value", "hold_s", "verify"} and "value" in step,
               w, "a word, or {register:, value:, hold_s:, verify:}", step)
        reg_name = step.get("register", default_register)
        expect(isinstance(reg_name, str) and reg_name in regs and regs[reg_name].writable
               and regs[reg_name].words == 1, f"{w}.register",
               "a writable 16-bit register of the profile", reg_name)
        reg = regs[reg_name]
        lo, hi = reg.raw_range()
        expect(_int(step["value"]) and lo <= step["value"] <= hi, f"{w}.value", f"a raw value {lo}..{hi}",
               step["value"])
        h = step.get("hold_s", hold_s)
        expect(is_number(h) and 0 <= h <= 5.0, f"{w}.hold_s", "0..5 s", h)
        verify = step.get("verify", False)
        expect(isinstance(verify, bool), f"{w}.verify", "true or false", verify)
        out.append(CommandStep(reg_name, int(step["value"]), float(h), verify))
    return tuple(out)


def _role(doc: dict[str, Any], key: str, regs: Mapping[str, Register], src: str, *, required: bool,
          writable: bool = False) -> str | None:
    name = doc.get(key)
    if name is None and not required:
        return None
    expect(isinstance(name, str) and name in regs, f"{src}: {key}", "the name of a register of the profile", name)
    if writable:
        expect(regs[str(name)].writable, f"{src}: {key}", "a writable register", name)
    return str(name)


def _ramp_rates(reg: Register, form: str, max_frequency_hz: float) -> tuple[float, float]:
    """The ramp rates (Hz/s) a ramp register takes: its range as such (``rate``), or the maximum
    frequency over its range of times (``time_to_max``; no shortest time: no fastest rate)."""
    lo, hi = reg.valid_range()
    if form == "rate":
        return lo, hi
    return (max_frequency_hz / hi if hi > 0 else math.inf), (max_frequency_hz / lo if lo > 0 else math.inf)


_TOP_KEYS = {"profile", "description", "sources", "transport", "device", "registers", "setpoint", "speed",
             "angle", "revolutions", "max_frequency", "ramp", "status", "faults", "commands", "watchdog", "safety"}
_SAFETY_KEYS = {"register", "parameter", "role", "how", "value", "min", "max", "meaning", "default"}


def _safety(doc: Any, regs: Mapping[str, Register], device: DeviceDefaults, src: str) -> tuple[SafetySetting, ...]:
    doc = [] if doc is None else doc
    expect(isinstance(doc, list), f"{src}: safety", "a list of settings", doc)
    out = []
    for i, e in enumerate(doc):
        w = f"{src}: safety[{i}]"
        expect(isinstance(e, dict) and set(e) <= _SAFETY_KEYS and {"register", "parameter", "role", "how"} <= set(e),
               w, f"{{register:, parameter:, role:, how:, value: | min:/max:, meaning:, default:}} (keys "
               f"{sorted(_SAFETY_KEYS)})", e)
        name = e["register"]
        expect(isinstance(name, str) and name in regs, f"{w}.register", "a register of the profile", name)
        reg = regs[name]
        expect(isinstance(e["parameter"], str) and bool(e["parameter"]), f"{w}.parameter",
               "the drive's name of the parameter (e.g. P9.04)", e["parameter"])
        expect(e["role"] in SAFETY_ROLES, f"{w}.role", f"one of {list(SAFETY_ROLES)}", e["role"])
        expect(e["how"] in ("set", "check"), f"{w}.how", "'set' (written once, read back) or 'check' (read only)",
               e["how"])
        has_value = "value" in e
        expect(has_value != ("min" in e or "max" in e), w, "either value: or a range min:/max:", sorted(e))
        for k in ("value", "min", "max", "default"):
            if k in e:
                expect(is_number(e[k]) and reg.in_range(e[k]) if reg.writable else is_number(e[k]), f"{w}.{k}",
                       f"a number the register holds ({reg.valid_range()})", e[k])
        expect(e["how"] == "check" or (has_value and reg.writable), f"{w}.how",
               "'check' (a range or a read-only register cannot be set)", e["how"])
        expect(isinstance(e.get("meaning", ""), str), f"{w}.meaning", "a string", e.get("meaning"))
        if e["role"] == "reference_frequency":
            expect(has_value and device.reference_frequency_hz is not None
                   and e["value"] == device.reference_frequency_hz, f"{w}.value",
                   f"device.reference_frequency_hz ({device.reference_frequency_hz}), what the scaling rests on",
                   e.get("value"))
        num = {k: None if e.get(k) is None else float(e[k]) for k in ("value", "min", "max", "default")}
        out.append(SafetySetting(name, e["parameter"], e["role"], e["how"], value=num["value"], min=num["min"],
                                 max=num["max"], meaning=e.get("meaning", ""), default=num["default"]))
    expect(len({s.register for s in out}) == len(out), f"{src}: safety", "each register once",
           [s.register for s in out])
    return tuple(out)


def parse_profile(doc: Any, source: str = "<profile>") -> DriveProfile:
    """Validate a loaded YAML document and build the frozen :class:`DriveProfile`.

    Every error is a :class:`RegisterMapError` naming the key, what was expected and what came."""
    src = source
    expect(isinstance(doc, dict), src, "a mapping (a drive profile)", type(doc).__name__)
    extra = sorted(str(k) for k in set(doc) - _TOP_KEYS)
    expect(not extra, src, f"only keys {sorted(_TOP_KEYS)}", extra)
    name = doc.get("profile")
    expect(isinstance(name, str) and bool(name), f"{src}: profile", "the profile's name", name)
    transport = _transport(doc.get("transport"), src)
    dev_doc = doc.get("device", {}) or {}
    expect(isinstance(dev_doc, dict), f"{src}: device", "a mapping", dev_doc)
    extra = sorted(str(k) for k in set(dev_doc) - _DEVICE_KEYS)
    expect(not extra, f"{src}: device", f"only keys {sorted(_DEVICE_KEYS)} (the frequency and ramp limits are "
           "the min/max of the set-point and ramp registers)", extra)
    for k, v in dev_doc.items():
        expect(is_number(v) and v > 0, f"{src}: device.{k}", "a positive number", v)
    regs = parse_registers(doc.get("registers"), dict(dev_doc), src)
    for r in regs.values():
        if r.writable and r.words > 1:
            expect(0x10 in transport.functions, f"{src}: registers.{r.name}",
                   "a 16-bit register (the drive does not answer FC 16, needed for a 32-bit write)", r.type)
        if r.function == "input":
            expect(0x04 in transport.functions, f"{src}: registers.{r.name}.function",
                   "'holding' (the drive does not answer FC 04)", r.function)
    setpoint = _role(doc, "setpoint", regs, src, required=True, writable=True)
    speed = _role(doc, "speed", regs, src, required=True)
    angle = _role(doc, "angle", regs, src, required=False)
    revolutions = _role(doc, "revolutions", regs, src, required=False)
    max_freq = _role(doc, "max_frequency", regs, src, required=False)
    assert setpoint is not None and speed is not None
    sp = regs[setpoint]
    expect(sp.min is not None and sp.max is not None, f"{src}: registers.{setpoint}.min/max",
           "the declared set-point range (the drive's frequency limits, Hz)", (sp.min, sp.max))
    assert sp.min is not None and sp.max is not None

    # ramp
    ramp: RampSpec | None = None
    min_ramp, max_ramp = 0.0, 100.0
    if doc.get("ramp") is not None:
        rd = doc["ramp"]
        expect(isinstance(rd, dict) and set(rd) == {"registers", "form"}, f"{src}: ramp",
               "{registers: [...], form: rate|time_to_max}", rd)
        expect(rd["form"] in RAMP_FORMS, f"{src}: ramp.form", "'rate' (Hz/s) or 'time_to_max' (s)", rd["form"])
        expect(isinstance(rd["registers"], list) and bool(rd["registers"]) and all(
            isinstance(r, str) and r in regs and regs[r].writable for r in rd["registers"]),
            f"{src}: ramp.registers", "writable registers of the profile", rd["registers"])
        ramp = RampSpec(tuple(rd["registers"]), rd["form"])
        first = regs[ramp.registers[0]]
        if ramp.form == "rate":
            expect(first.max is not None, f"{src}: registers.{first.name}.max", "a declared limit", first.max)
            assert first.max is not None
        else:
            expect(first.min is not None and first.min > 0, f"{src}: registers.{first.name}.min",
                   "the shortest ramp time (> 0 s)", first.min)
            assert first.min is not None
        # the ramp rates every ramp register takes (Hz/s): a rate as such, a time as max. frequency / time
        rates = [_ramp_rates(regs[r], ramp.form, sp.max) for r in ramp.registers]
        min_ramp, max_ramp = max(0.0, *(lo for lo, _ in rates)), min(hi for _, hi in rates)
        expect(min_ramp <= max_ramp, f"{src}: ramp.registers", "ranges sharing at least one ramp rate",
               rates)
    device = DeviceDefaults(max_frequency_hz=sp.max, min_frequency_hz=sp.min, max_ramp_hz_per_s=max_ramp,
                            min_ramp_hz_per_s=min_ramp,
                            **{k: float(v) for k, v in dev_doc.items()})

    # status
    sd = doc.get("status")
    expect(isinstance(sd, dict) and "register" in sd and "flags" in sd and set(sd) <= {"register", "flags",
           "idle_word"}, f"{src}: status", "{register:, flags: {...}, idle_word:}", sd)
    status_reg = _role(sd, "register", regs, f"{src}: status", required=True)
    expect(isinstance(sd["flags"], dict) and "enabled" in sd["flags"], f"{src}: status.flags",
           "a mapping flag -> bit spec with at least 'enabled'", sd["flags"])
    flags = {str(k): _flag(v, f"{src}: status.flags.{k}") for k, v in sd["flags"].items()}
    for r in regs.values():
        expect(r.reads_flag is None or r.reads_flag in (*CANONICAL_FLAGS, *flags),
               f"{src}: registers.{r.name}.reads_flag", "a canonical or declared status flag", r.reads_flag)
    idle = sd.get("idle_word", 0)
    expect(_int(idle) and 0 <= idle <= 0xFFFF, f"{src}: status.idle_word", "0..65535", idle)
    assert status_reg is not None
    status = StatusTable(status_reg, flags, idle)

    # faults
    fd = doc.get("faults")
    expect(isinstance(fd, dict) and set(fd) <= {"register", "codes", "kinds"} and "codes" in fd, f"{src}: faults",
           "{register:, codes: {...}, kinds: {...}}", fd)
    fault_reg = _role(fd, "register", regs, f"{src}: faults", required=False)
    codes = fd["codes"]
    expect(isinstance(codes, dict) and codes.get(0) is not None and all(_int(c) and 0 <= c <= 0xFFFF for c in codes),
           f"{src}: faults.codes", "a mapping of integer codes 0..65535 -> names, with 0", codes)
    kinds = fd.get("kinds", {}) or {}
    expect(isinstance(kinds, dict) and set(kinds) <= set(FAULT_KINDS.values())
           and all(_int(c) and c in codes and c != 0 for c in kinds.values()), f"{src}: faults.kinds",
           f"a mapping from {sorted(FAULT_KINDS.values())} to non-zero codes of the table", kinds)
    faults = FaultTable(fault_reg, {int(k): str(v) for k, v in codes.items()}, dict(kinds))

    # commands
    cd = doc.get("commands")
    expect(isinstance(cd, dict) and cd.get("model") in ("control_word", "registers"), f"{src}: commands",
           "{model: control_word|registers, ...}", cd)
    allowed = {"model", "register", "hold_s", "reset_reboot_s", "repeat_quick_stop", *COMMANDS, *OPTIONAL_COMMANDS}
    expect(set(cd) <= allowed, f"{src}: commands", f"only keys {sorted(allowed)}", sorted(map(str, cd)))
    hold = cd.get("hold_s", 0.0)
    expect(is_number(hold) and 0 <= hold <= 5.0, f"{src}: commands.hold_s", "0..5 s", hold)
    control: str | None = None
    if cd["model"] == "control_word":
        control = _role(cd, "register", regs, f"{src}: commands", required=True, writable=True)
    seqs = {}
    for c in COMMANDS:
        expect(c in cd, f"{src}: commands", f"a sequence for each of {list(COMMANDS)}", f"no {c!r}")
        seqs[c] = _steps(cd[c], f"{src}: commands.{c}", control, regs, float(hold))
    for c in OPTIONAL_COMMANDS:
        if c in cd:
            seqs[c] = _steps(cd[c], f"{src}: commands.{c}", control, regs, float(hold))
    reboot = cd.get("reset_reboot_s", 0.0)
    expect(is_number(reboot) and 0 <= reboot <= 30.0, f"{src}: commands.reset_reboot_s", "0..30 s", reboot)
    repeat_qs = cd.get("repeat_quick_stop", True)
    expect(isinstance(repeat_qs, bool), f"{src}: commands.repeat_quick_stop", "true or false", repeat_qs)
    commands = CommandModel(cd["model"], seqs, float(reboot), repeat_qs)


    # watchdog: never off
    wd = doc.get("watchdog")
    expect(isinstance(wd, dict) and set(wd) <= {"register", "timeout_s", "min_s", "refresh", "drive_default_s",
                                                 "parameter"},
           f"{src}: watchdog", "{register:, timeout_s:, min_s:, refresh: <register>|any_request|{rewrite: <register>}, "
           "drive_default_s:}", wd)
    wd_reg = _role(wd, "register", regs, f"{src}: watchdog", required=True, writable=True)
    t, m = wd.get("timeout_s"), wd.get("min_s", 0.0)
    expect(is_number(t) and t > 0, f"{src}: watchdog.timeout_s",
           "a time-out > 0 s (a profile whose communication watchdog is off is refused)", t)
    expect(t >= MIN_WATCHDOG_TIMEOUT_S, f"{src}: watchdog.timeout_s", f"at least {MIN_WATCHDOG_TIMEOUT_S} s "
           "(the station refreshes the watchdog every 0.2 s)", t)
    expect(is_number(m) and 0 <= m <= t, f"{src}: watchdog.min_s", f"0..timeout_s ({t} s)", m)
    assert wd_reg is not None
    expect(regs[wd_reg].in_range(t) and t >= regs[wd_reg].scale, f"{src}: watchdog.timeout_s",
           f"a value register {wd_reg!r} holds ({regs[wd_reg].valid_range()})", t)
    refresh = wd.get("refresh", "any_request")
    rewrite: str | None = None
    if isinstance(refresh, dict):
        rewrite = refresh.get("rewrite")
        expect(set(refresh) == {"rewrite"} and isinstance(rewrite, str) and rewrite in regs
               and regs[rewrite].writable and not regs[rewrite].eeprom, f"{src}: watchdog.refresh.rewrite",
               "a writable RAM register (it is written every refresh)", rewrite)
        refresh = "any_request"
    elif refresh != "any_request":
        expect(isinstance(refresh, str) and refresh in regs and regs[refresh].writable, f"{src}: watchdog.refresh",
               "'any_request' or a writable register", refresh)
    default_s = wd.get("drive_default_s")
    expect(default_s is None or (is_number(default_s) and regs[wd_reg].in_range(default_s)),
           f"{src}: watchdog.drive_default_s", "the drive's factory time-out (s, 0: off)", default_s)
    parameter = wd.get("parameter", "")
    expect(isinstance(parameter, str), f"{src}: watchdog.parameter", "the drive's name of the parameter", parameter)
    watchdog = WatchdogSpec(wd_reg, float(t), float(m), None if refresh == "any_request" else str(refresh), rewrite,
                            None if default_s is None else float(default_s), parameter)

    device = replace(device, default_watchdog_timeout_s=watchdog.timeout_s)
    sources = doc.get("sources", []) or []
    expect(isinstance(sources, list) and all(isinstance(s, str) for s in sources), f"{src}: sources",
           "a list of strings", sources)
    retry = transport.retry_writes
    expect(isinstance(retry, tuple) and all(isinstance(n, str) and n in regs and regs[n].writable
                                            and n not in commands.registers - {setpoint} for n in retry),
           f"{src}: transport.retry_writes", "writable registers of the profile other than command registers "
           "(a command word is sent once)", retry)
    safety = _safety(doc.get("safety"), regs, device, src)
    return DriveProfile(name, str(doc.get("description", "")), tuple(sources), transport, regs, device, setpoint,
                        speed, status, faults, commands, watchdog, ramp, angle, revolutions, max_freq, source,
                        tuple(f for f in flags if f not in CANONICAL_FLAGS), safety=safety)


def profile_path(name_or_path: str | Path) -> Path:
    """A shipped profile by name (``config/drives/<name>.yaml``) or a YAML file by path."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.is_file():
        return p
    return Path(config_file(f"{PROFILE_DIR}/{name_or_path}.yaml"))


def shipped_profiles() -> list[str]:
    """Names of the profiles shipped in ``config/drives/``."""
    folder = config_file(f"{PROFILE_DIR}/{DEFAULT_PROFILE}.yaml").parent
    return sorted(p.stem for p in folder.glob("*.yaml"))


class _UniqueKeys(yaml.SafeLoader):  # type: ignore[misc]  # PyYAML ships no annotations (types-PyYAML not installed)
    """SafeLoader that refuses a key written twice in one mapping, naming both lines (not libyaml's: a
    deeply nested document would crash its composer, which recurses in C)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        lines: dict[Any, int] = {}
        for k, _ in node.value:
            key = self.construct_object(k, deep=True)
            line = k.start_mark.line + 1
            if isinstance(key, str | int | float | bool) and lines.setdefault(key, line) != line:
                raise yaml.constructor.ConstructorError(None, None, f"key {key!r} on line {lines[key]} and again "
                                                        f"on line {line}", k.start_mark)
        mapping: dict[Any, Any] = super().construct_mapping(node, deep)
        return mapping


def load_profile(name_or_path: str | Path | None = None) -> DriveProfile:
    """Load and validate a profile (default: the station's own crank controller, ``sinecal-crank``)."""
    try:
        p = profile_path(name_or_path or DEFAULT_PROFILE)
    except FileNotFoundError as exc:
        raise RegisterMapError(f"drive profile {name_or_path!r}: expected a shipped profile "
                               f"({', '.join(shipped_profiles())}) or a .yaml path") from exc
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise RegisterMapError(f"drive profile {p}: cannot read it ({exc})") from exc
    return _parsed_profile(text, str(p))


@functools.lru_cache(maxsize=32)
def _parsed_profile(text: str, path: str) -> DriveProfile:
    """The profile ``text`` read from ``path``, parsed once per text and path (a station configuration
    names its profile and is parsed at every recording read; the result is frozen, so it is shared)."""
    try:
        doc = yaml.load(text, Loader=_UniqueKeys)  # a SafeLoader that refuses a key written twice
    except yaml.YAMLError as exc:
        raise RegisterMapError(f"{path}: not valid YAML: {exc}") from exc
    return replace(parse_profile(doc, path), text=text)
