"""One register of a drive profile: where it is on the wire, how it is read and written, how its
raw words become a physical value.

Physical value = raw * scale + offset, in the register's ``unit``.  A profile writes each register as
its drive's manual prints it (``address`` with the manual's ``numbering``: 0-based wire addresses,
1-based register numbers, or Modicon references such as 40101) and the scaling as the manual gives
it (``scale``/``offset``, or a normalised form such as "16384 = 100 % of the reference frequency");
:func:`parse_register` turns that into the wire address and one ``scale``.  A writable register may
declare ``min``/``max`` (physical units): the driver refuses a value outside them before sending,
the emulator answers exception 03 ILLEGAL DATA VALUE.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from drivers.motor.errors import MotorValueError, RegisterMapError

# type name -> (number of 16-bit words, signed)
_TYPES: dict[str, tuple[int, bool]] = {
    "uint16": (1, False),
    "int16": (1, True),
    "uint32": (2, False),
    "int32": (2, True),
}
FUNCTIONS = {"holding": 0x03, "input": 0x04}  # read function code of each register kind
WORD_ORDERS = ("high_first", "low_first")
MEMORIES = ("ram", "eeprom")
NUMBERINGS = (0, 1, "modicon")


@dataclass(frozen=True)
class Register:
    """One register (or a 32-bit pair): ``address`` is the 0-based wire address of the first word.

    ``function``: ``holding`` (read FC 03, written FC 06/16) or ``input`` (read FC 04, read-only);
    ``word_order`` of a 32-bit value; ``memory``: ``ram`` or ``eeprom`` (an EEPROM-backed register
    wears out: the driver writes it only when its value changes, never in a loop)."""

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
    function: str = "holding"
    word_order: str = "high_first"
    memory: str = "ram"
    reads_flag: str | None = None  # a command register that reads back a status flag (1 while it is set)

    @property
    def words(self) -> int:
        """Number of 16-bit words the register occupies."""
        return _TYPES[self.type][0]

    @property
    def writable(self) -> bool:
        return self.access == "rw"

    @property
    def eeprom(self) -> bool:
        return self.memory == "eeprom"

    @property
    def read_function(self) -> int:
        """Modbus function code that reads this register (03 or 04)."""
        return FUNCTIONS[self.function]

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

    def raw_of(self, value: float) -> int:
        """Physical value -> raw integer (rounded to the register's resolution); MotorValueError outside
        what the type holds."""
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
        return raw

    def words_of_raw(self, raw: int) -> list[int]:
        """Raw integer -> 16-bit words in the register's word order."""
        raw &= (1 << (16 * self.words)) - 1
        high_first = [(raw >> (16 * (self.words - 1 - i))) & 0xFFFF for i in range(self.words)]
        return high_first if self.word_order == "high_first" else high_first[::-1]

    def encode(self, value: float) -> list[int]:
        """Physical value (in ``unit``) -> list of 16-bit words (in the register's word order)."""
        return self.words_of_raw(self.raw_of(value))

    def decode_raw(self, words: Sequence[int]) -> int:
        """Words (in the register's word order) -> raw integer, sign applied."""
        if len(words) != self.words:
            raise MotorValueError(f"register {self.name!r}: expected {self.words} word(s), got {len(words)}")
        ordered = list(words) if self.word_order == "high_first" else list(words)[::-1]
        raw = 0
        for w in ordered:
            raw = (raw << 16) | (int(w) & 0xFFFF)
        bits = 16 * self.words
        if _TYPES[self.type][1] and raw >= 1 << (bits - 1):
            raw -= 1 << bits
        return raw

    def decode(self, words: Sequence[int]) -> float:
        """Words -> physical value in ``unit``."""
        return self.decode_raw(words) * self.scale + self.offset


def expect(cond: bool, where: str, expected: str, got: Any) -> None:
    """Raise :class:`RegisterMapError` ``<where>: expected <expected>, got <got>`` unless ``cond``."""
    if not cond:
        raise RegisterMapError(f"{where}: expected {expected}, got {got!r}")


def is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def wire_address(number: Any, numbering: Any, function: str, where: str) -> int:
    """The 0-based wire address of a register the manual numbers ``number`` (``numbering`` 0: as on the
    wire; 1: register numbers from 1; ``modicon``: 4xxxx holding / 3xxxx input references)."""
    expect(isinstance(number, int) and not isinstance(number, bool), f"{where}.address", "an integer", number)
    expect(numbering in NUMBERINGS, f"{where}.numbering", "0 (wire address), 1 (register number) or "
           "'modicon' (40001-based holding, 30001-based input references)", numbering)
    addr: int
    if numbering == 0:
        addr = number
    elif numbering == 1:
        addr = number - 1
    else:
        base = 40001 if function == "holding" else 30001
        expect(base <= number <= base + 0xFFFF, f"{where}.address",
               f"a Modicon reference {base}..{base + 0xFFFF} for a {function} register", number)
        addr = number - base
    expect(0 <= addr <= 0xFFFF, f"{where}.address", "a wire address 0..65535 after numbering", addr)
    return addr


_REGISTER_KEYS = {"address", "numbering", "function", "type", "scale", "offset", "normalised", "unit", "access",
                  "memory", "word_order", "description", "min", "max", "reads_flag"}


def parse_register(name: str, spec: Any, device: Mapping[str, float | None], source: str = "") -> Register:
    """Validate one register of a profile's ``registers`` section.

    ``normalised: {raw: 16384, full_scale: reference_frequency_hz}`` means raw 16384 is the value of
    that ``device`` key (100 %): scale = full_scale / raw (instead of ``scale``)."""
    where = f"{source}: registers.{name}" if source else f"registers.{name}"
    expect(isinstance(spec, dict), where, "a mapping", spec)
    unknown = sorted(str(k) for k in set(spec) - _REGISTER_KEYS)
    expect(not unknown, where, f"only keys {sorted(_REGISTER_KEYS)}", unknown)
    function = spec.get("function", "holding")
    expect(isinstance(function, str) and function in FUNCTIONS, f"{where}.function",
           "'holding' (FC 03/06/16) or 'input' (FC 04)", function)
    addr = wire_address(spec.get("address"), spec.get("numbering", 0), function, where)
    typ = spec.get("type")
    expect(isinstance(typ, str) and typ in _TYPES, f"{where}.type", f"one of {sorted(_TYPES)}", typ)
    if "normalised" in spec:
        expect("scale" not in spec, where, "either scale or normalised", "both")
        norm = spec["normalised"]
        expect(isinstance(norm, dict) and set(norm) == {"raw", "full_scale"}, f"{where}.normalised",
               "{raw: <raw value of 100 %>, full_scale: <a device key>}", norm)
        expect(is_number(norm["raw"]) and norm["raw"] != 0, f"{where}.normalised.raw", "a non-zero number",
               norm["raw"])
        full = device.get(norm["full_scale"]) if isinstance(norm["full_scale"], str) else None
        expect(full is not None and is_number(full) and full != 0, f"{where}.normalised.full_scale",
               f"a device key with a non-zero value (have {sorted(k for k, v in device.items() if v)})",
               norm["full_scale"])
        assert full is not None
        scale = float(full) / float(norm["raw"])
    else:
        scale = spec.get("scale", 1.0)
        expect(is_number(scale) and scale != 0, f"{where}.scale", "a finite non-zero number", scale)
    offset = spec.get("offset", 0.0)
    expect(is_number(offset), f"{where}.offset", "a number", offset)
    access = spec.get("access", "rw" if function == "holding" else "r")
    expect(access in ("r", "rw"), f"{where}.access", "'r' or 'rw'", access)
    expect(not (access == "rw" and function == "input"), f"{where}.access", "'r' for an input register", access)
    memory = spec.get("memory", "ram")
    expect(isinstance(memory, str) and memory in MEMORIES, f"{where}.memory", "'ram' or 'eeprom'", memory)
    order = spec.get("word_order", "high_first")
    expect(isinstance(order, str) and order in WORD_ORDERS, f"{where}.word_order", "'high_first' or 'low_first'", order)
    unit = spec.get("unit", "")
    expect(isinstance(unit, str), f"{where}.unit", "a string", unit)
    desc = str(spec.get("description", ""))
    bounds: dict[str, float | None] = {}
    for key in ("min", "max"):
        v = spec.get(key)
        expect(v is None or is_number(v), f"{where}.{key}", "a finite number (in the register's unit)", v)
        bounds[key] = None if v is None else float(v)
    flag = spec.get("reads_flag")
    expect(flag is None or isinstance(flag, str), f"{where}.reads_flag", "the name of a status flag", flag)
    reg = Register(name, addr, typ, float(scale), float(offset), unit, access, desc, bounds["min"], bounds["max"],
                   function, order, memory, flag)
    type_lo, type_hi = Register(name, addr, typ, float(scale), float(offset)).valid_range()
    lo, hi = reg.valid_range()
    expect(type_lo <= lo <= hi <= type_hi, f"{where}.min/max",
           f"min <= max within what {typ} x {scale:g} holds [{type_lo:g}, {type_hi:g}]", (lo, hi))
    return reg


def parse_registers(doc: Any, device: Mapping[str, float | None], source: str) -> dict[str, Register]:
    """The ``registers`` section: every register valid, no wire address used twice (per function)."""
    expect(isinstance(doc, dict) and bool(doc), f"{source}: registers", "a non-empty mapping", doc)
    regs = {str(name): parse_register(str(name), spec, device, source) for name, spec in doc.items()}
    used: dict[tuple[str, int], str] = {}
    for reg in regs.values():
        for a in range(reg.address, reg.address + reg.words):
            key = ("shared", a)  # holding and input registers share one address space on most drives
            expect(key not in used, f"{source}: registers.{reg.name}", f"address {a} not used twice",
                   f"overlap with {used.get(key)!r}")
            used[key] = reg.name
    return regs
