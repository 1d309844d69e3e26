"""The motor-controller register map: loaded once from ``config/motor_registers.yaml``
(shipped as ``sinecal_config``).

Both the driver and the emulator use :class:`RegisterMap`; nothing else declares an address,
a type, a scaling or a valid range.  Physical value = raw * scale + offset, in the register's ``unit``.
A writable register may declare ``min``/``max`` (physical units): the driver refuses a value outside
them before sending, the emulator answers exception 03 ILLEGAL DATA VALUE.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from sinecal_config import config_file

from drivers.motor.errors import MotorValueError, RegisterMapError

DEFAULT_REGISTER_MAP_PATH = config_file("motor_registers.yaml")

# type name -> (number of 16-bit words, signed)
_TYPES: dict[str, tuple[int, bool]] = {
    "uint16": (1, False),
    "int16": (1, True),
    "uint32": (2, False),
    "int32": (2, True),
}


@dataclass(frozen=True)
class Register:
    """One register (or a 32-bit pair): address is the 0-based wire address of the first word."""

    name: str
    address: int
    type: str
    scale: float = 1.0
    offset: float = 0.0
    unit: str = ""
    access: str = "rw"
    description: str = ""
    min: float | None = None
    max: float | None = None

    @property
    def words(self) -> int:
        """Number of 16-bit words the register occupies."""
        return _TYPES[self.type][0]

    @property
    def writable(self) -> bool:
        return self.access == "rw"

    def raw_range(self) -> tuple[int, int]:
        """Smallest and largest raw integer of the type."""
        words, signed = _TYPES[self.type]
        bits = 16 * words
        return (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)

    def valid_range(self) -> tuple[float, float]:
        """[min, max] in ``unit``: the declared range, else what the type can hold."""
        lo, hi = self.raw_range()
        lo_v, hi_v = sorted((lo * self.scale + self.offset, hi * self.scale + self.offset))
        return (lo_v if self.min is None else self.min, hi_v if self.max is None else self.max)

    def in_range(self, value: float) -> bool:
        """``value`` (in ``unit``) is finite and within :meth:`valid_range` (to half a raw step)."""
        lo, hi = self.valid_range()
        tol = 0.5 * abs(self.scale) * 1e-6
        return math.isfinite(value) and lo - tol <= value <= hi + tol

    def check(self, value: float) -> None:
        """Raise :class:`MotorValueError` (expected range, received value) unless :meth:`in_range`."""
        if not self.in_range(value):
            lo, hi = self.valid_range()
            unit = f" {self.unit}" if self.unit else ""
            raise MotorValueError(f"register {self.name!r}: expected {lo:g}..{hi:g}{unit}, got {value!r}{unit}")

    def encode(self, value: float) -> list[int]:
        """Physical value (in ``unit``) -> list of 16-bit words (high word first)."""
        if not math.isfinite(value):
            raise MotorValueError(f"register {self.name!r}: expected a finite value, got {value!r}")
        raw = round((value - self.offset) / self.scale)
        lo, hi = self.raw_range()
        if not lo <= raw <= hi:
            raise MotorValueError(
                f"register {self.name!r}: {value} {self.unit} is raw {raw}, outside the {self.type} range "
                f"[{lo}, {hi}] (i.e. [{lo * self.scale + self.offset}, {hi * self.scale + self.offset}] "
                f"{self.unit})"
            )
        raw &= (1 << (16 * self.words)) - 1
        return [(raw >> (16 * (self.words - 1 - i))) & 0xFFFF for i in range(self.words)]

    def decode_raw(self, words: Sequence[int]) -> int:
        """Words (high first) -> raw integer, sign applied."""
        if len(words) != self.words:
            raise MotorValueError(f"register {self.name!r}: expected {self.words} word(s), got {len(words)}")
        raw = 0
        for w in words:
            raw = (raw << 16) | (int(w) & 0xFFFF)
        bits = 16 * self.words
        if _TYPES[self.type][1] and raw >= 1 << (bits - 1):
            raw -= 1 << bits
        return raw

    def decode(self, words: Sequence[int]) -> float:
        """Words (high first) -> physical value in ``unit``."""
        return self.decode_raw(words) * self.scale + self.offset


@dataclass(frozen=True)
class DeviceDefaults:
    """Controller-wide settings (SI units: Hz, Hz/s, s)."""

    device_id: int = 1
    max_frequency_hz: float = 100.0
    min_frequency_hz: float = 0.0
    default_ramp_hz_per_s: float = 5.0
    max_ramp_hz_per_s: float = 100.0
    stop_deceleration_hz_per_s: float = 50.0
    default_watchdog_timeout_s: float = 1.0


# DeviceDefaults fields that come from a register's declared range (declared there, once)
_FROM_RANGES = {"min_frequency_hz": ("frequency_setpoint", "min"),
                "max_frequency_hz": ("frequency_setpoint", "max"),
                "max_ramp_hz_per_s": ("acceleration_ramp", "max")}


@dataclass(frozen=True)
class RegisterMap:
    """All registers by name, the status-word bits and the fault-code names."""

    registers: Mapping[str, Register]
    status_bits: Mapping[str, int]
    fault_codes: Mapping[int, str]
    device: DeviceDefaults

    def __getitem__(self, name: str) -> Register:
        try:
            return self.registers[name]
        except KeyError:
            raise KeyError(f"no register {name!r} in the map (have: {', '.join(self.registers)})") from None

    def span(self, names: Sequence[str]) -> tuple[int, int]:
        """(first address, word count) of the contiguous block covering ``names``."""
        regs = [self[n] for n in names]
        start = min(r.address for r in regs)
        end = max(r.address + r.words for r in regs)
        return start, end - start

    def decode_status(self, word: int) -> dict[str, bool]:
        """Status word -> {bit name: set?}."""
        return {name: bool(word >> bit & 1) for name, bit in self.status_bits.items()}

    def encode_status(self, flags: Mapping[str, bool]) -> int:
        """{bit name: set?} -> status word; unknown names are an error."""
        word = 0
        for name, on in flags.items():
            if name not in self.status_bits:
                raise KeyError(f"unknown status bit {name!r} (have: {', '.join(self.status_bits)})")
            if on:
                word |= 1 << self.status_bits[name]
        return word

    def fault_name(self, code: int) -> str:
        return self.fault_codes.get(code, f"unknown_fault_{code}")

    def fault_code(self, name: str) -> int:
        for code, n in self.fault_codes.items():
            if n == name:
                return code
        raise KeyError(f"unknown fault {name!r} (have: {', '.join(self.fault_codes.values())})")


def _expect(cond: bool, where: str, expected: str, got: Any) -> None:
    if not cond:
        raise RegisterMapError(f"{where}: expected {expected}, got {got!r}")


def _parse_register(name: str, spec: Any) -> Register:
    where = f"registers.{name}"
    _expect(isinstance(spec, dict), where, "a mapping", spec)
    allowed = {"address", "type", "scale", "offset", "unit", "access", "description", "min", "max"}
    unknown = set(spec) - allowed
    _expect(not unknown, where, f"only keys {sorted(allowed)}", sorted(unknown))
    addr = spec.get("address")
    _expect(isinstance(addr, int) and not isinstance(addr, bool) and 0 <= addr <= 0xFFFF,
            f"{where}.address", "an integer 0..65535", addr)
    typ = spec.get("type")
    _expect(typ in _TYPES, f"{where}.type", f"one of {sorted(_TYPES)}", typ)
    scale = spec.get("scale", 1.0)
    _expect(isinstance(scale, int | float) and not isinstance(scale, bool) and scale != 0
            and math.isfinite(scale), f"{where}.scale", "a finite non-zero number", scale)
    offset = spec.get("offset", 0.0)
    _expect(isinstance(offset, int | float) and math.isfinite(offset), f"{where}.offset", "a number", offset)
    access = spec.get("access", "rw")
    _expect(access in ("r", "rw"), f"{where}.access", "'r' or 'rw'", access)
    unit = spec.get("unit", "")
    _expect(isinstance(unit, str), f"{where}.unit", "a string", unit)
    desc = str(spec.get("description", ""))
    bounds: dict[str, float | None] = {}
    for key in ("min", "max"):
        v = spec.get(key)
        _expect(v is None or (isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)),
                f"{where}.{key}", "a finite number (in the register's unit)", v)
        bounds[key] = None if v is None else float(v)
    reg = Register(name, addr, typ, float(scale), float(offset), unit, access, desc, bounds["min"],
                   bounds["max"])
    type_lo, type_hi = Register(name, addr, typ, float(scale), float(offset)).valid_range()
    lo, hi = reg.valid_range()
    _expect(type_lo <= lo <= hi <= type_hi, f"{where}.min/max",
            f"min <= max within what {typ} x {scale:g} holds [{type_lo:g}, {type_hi:g}]", (lo, hi))
    return reg


def parse_register_map(doc: Any, source: str = "<register map>") -> RegisterMap:
    """Validate a loaded YAML document and build the frozen :class:`RegisterMap`."""
    _expect(isinstance(doc, dict), source, "a mapping with 'registers', 'status_bits', 'fault_codes'", doc)
    regs_doc = doc.get("registers")
    _expect(isinstance(regs_doc, dict) and bool(regs_doc), f"{source}: registers", "a non-empty mapping", regs_doc)
    regs = {name: _parse_register(name, spec) for name, spec in regs_doc.items()}
    used: dict[int, str] = {}
    for reg in regs.values():
        for a in range(reg.address, reg.address + reg.words):
            _expect(a not in used, f"{source}: registers.{reg.name}", f"address {a} not used twice",
                    f"overlap with {used.get(a)!r}")
            used[a] = reg.name
    bits = doc.get("status_bits", {})
    _expect(isinstance(bits, dict), f"{source}: status_bits", "a mapping name -> bit", bits)
    for bname, bit in bits.items():
        _expect(isinstance(bit, int) and 0 <= bit <= 15, f"{source}: status_bits.{bname}", "a bit 0..15", bit)
    faults = doc.get("fault_codes", {0: "none"})
    _expect(isinstance(faults, dict), f"{source}: fault_codes", "a mapping code -> name", faults)
    for code in faults:
        _expect(isinstance(code, int) and 0 <= code <= 0xFFFF, f"{source}: fault_codes", "integer codes",
                code)
    dev_doc = doc.get("device", {})
    _expect(isinstance(dev_doc, dict), f"{source}: device", "a mapping", dev_doc)
    known = set(DeviceDefaults.__dataclass_fields__) - set(_FROM_RANGES)
    extra = sorted(set(dev_doc) - known)
    _expect(not extra, f"{source}: device", f"only keys {sorted(known)} (the frequency and ramp limits "
            "are the min/max of registers frequency_setpoint and acceleration_ramp)", extra)
    required = ("enable", "frequency_setpoint", "acceleration_ramp", "actual_speed", "crank_angle",
                "status_word", "fault_code", "watchdog", "emergency_stop")
    missing = [r for r in required if r not in regs]
    _expect(not missing, f"{source}: registers", f"all of {list(required)}", f"missing {missing}")
    from_ranges = {}
    for fname, (rname, key) in _FROM_RANGES.items():
        value = getattr(regs[rname], key)
        _expect(value is not None, f"{source}: registers.{rname}.{key}", "a declared limit", value)
        from_ranges[fname] = value
    device = DeviceDefaults(**dev_doc, **from_ranges)
    return RegisterMap(regs, dict(bits), {int(k): str(v) for k, v in faults.items()}, device)


def load_register_map(path: str | Path | None = None) -> RegisterMap:
    """Load and validate the register map YAML (default: ``config/motor_registers.yaml``)."""
    p = Path(path) if path is not None else DEFAULT_REGISTER_MAP_PATH
    try:
        doc = yaml.safe_load(p.read_text())
    except yaml.YAMLError as exc:
        raise RegisterMapError(f"{p}: not valid YAML: {exc}") from exc
    return parse_register_map(doc, str(p))
