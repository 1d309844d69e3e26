"""How a certificate writes numbers, units and quantities for people (the DCC keeps full numbers).

* A value with its expanded uncertainty (GUM 7.2.6): U rounded to two significant digits, the value
  rounded to the same decimal place; both written with one power of ten (×10⁷) when the value is
  below 10⁻³ or from 10⁵ up, so the columns read alike.
* SI typography: a half-high dot between units, superscript powers (N·s/m, V·s²/m, mV/(V·N)).
* Quantities by their names ("stiffness of the transducer"), never internal keys.
"""

from __future__ import annotations

import math
import re

SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")
UNIT_TEXT = {"N*s/m": "N·s/m", "V*s^2/m": "V·s²/m", "mV/V/N": "mV/(V·N)", "mV/V*s^2/m": "mV·s²/(V·m)",
             "pC*s^2/m": "pC·s²/m", "degC": "°C", "deg": "°", "1": ""}
QUANTITY = {"S": "sensitivity (static limit of the dynamic sensitivity)",
            "k_f": "stiffness of the transducer", "b_f": "damping coefficient of the transducer",
            "k_c": "stiffness of the coupling", "b_c": "damping coefficient of the coupling",
            "m_e": "end mass of the transducer",
            "natural_frequency_hz": "natural frequency with the load mass, √(k_f/M)/(2π)",
            "series_stiffness": "series stiffness of transducer and coupling",
            "S_times_M": "sensitivity times moving mass", "damping_ratio": "damping ratio",
            "transducer_stiffness_alone": "stiffness of the transducer alone"}
SYMBOL = {"S": "S", "k_f": "k_f", "b_f": "b_f", "k_c": "k_c", "b_c": "b_c", "m_e": "m_e",
          "natural_frequency_hz": "f₀", "series_stiffness": "k_s", "S_times_M": "S·M", "damping_ratio": "ζ",
          "transducer_stiffness_alone": "k_f"}


def unit_text(unit: str) -> str:
    """A station unit string in SI typography."""
    return UNIT_TEXT.get(unit, unit.replace("*", "·").replace("^2", "²").replace("^-1", "⁻¹"))


def _exponent(value: float) -> int:
    if not value or not math.isfinite(value):
        return 0
    e = math.floor(math.log10(abs(value)))
    return 0 if -3 <= e < 5 else e


def _power(e: int) -> str:
    return f" ×10{str(e).translate(SUPERSCRIPT)}" if e else ""


def round2(u: float) -> float:
    """u to two significant digits."""
    return float(f"{u:.2g}")


def value_and_uncertainties(value: float, U: float, *others: float) -> tuple[str, ...]:
    """(value, U, *others) as text: U to two significant digits, the value to U's decimal place,
    others (e.g. u) to two significant digits; one power of ten for all (module docstring)."""
    e = _exponent(value)
    scale = 10.0**e
    Ur = round2(U / scale) if U > 0 else 0.0
    d = max(0, 1 - math.floor(math.log10(Ur))) if Ur > 0 else 6
    out = [f"{value / scale:.{d}f}{_power(e)}", f"{Ur:.{d}f}{_power(e)}"]
    for o in others:
        orr = round2(o / scale) if o > 0 else 0.0
        do = max(0, 1 - math.floor(math.log10(orr))) if orr > 0 else d
        out.append(f"{orr:.{do}f}{_power(e)}")
    return tuple(out)


def plain(value: float | None, digits: int = 6) -> str:
    """A value without an uncertainty, ``digits`` significant digits, SI power of ten."""
    if value is None or not math.isfinite(value):
        return "—"
    e = _exponent(value)
    m = value / 10.0**e
    d = max(0, digits - 1 - math.floor(math.log10(abs(m)))) if m else 0
    return f"{m:.{d}f}".rstrip("0").rstrip(".") + _power(e) if "." in f"{m:.{d}f}" else f"{m:.{d}f}{_power(e)}"


def _power_of_ten(m: re.Match[str]) -> str:
    return f"{m.group(1)}{_power(int(m.group(2)))}"


def typeset(text: str) -> str:
    """A sentence with the station's unit strings in SI typography (N*s/m -> N·s/m, V*s^2/m -> V·s²/m)
    and its numbers' powers of ten written ×10ⁿ (2.91e+07 -> 2.91 ×10⁷)."""
    for raw in ("mV/V*s^2/m", "pC*s^2/m", "V*s^2/m", "N*s/m"):
        text = text.replace(raw, unit_text(raw))
    text = text.replace("chi2/dof", "χ²/dof").replace("sqrt(", "√(")
    return re.sub(r"\b(\d+(?:\.\d+)?)e([+-]?\d+)\b", _power_of_ten, text)
