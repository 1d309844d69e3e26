"""What was calibrated: the measuring chain the configuration names (``conditioner.calibrated``).

The station measures the force signal after the conditioner, so an identification's S is the
sensitivity of transducer x conditioner in V/N.  A certificate states either

* **the chain** (``chain``): the transducer and the lab's conditioner as one measuring chain, S in
  V/N with the conditioner's gain inside; title and item say so; or
* **the transducer alone** (``transducer``): the conditioner is a calibrated reference standard of
  gain G (V/V, or V/pC for a charge amplifier) and, for a strain-gauge bridge, excitation E (V).
  S of the transducer = S_chain / (G E) in mV/V per N (x 1e3), S_chain / G in V/N (bridge output,
  no excitation stated) or in pC/N (charge amplifier).  The relative standard uncertainties of G and
  E (from the conditioner's certificate) enter the budget of S and of every quantity proportional
  to it (S M, S_dyn) as the source ``conditioner_gain``; k_f and b_f do not depend on them.

``item_budget`` rescales the stored budget (V/N) to the item's unit and adds that source.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from station.config import ConditionerConfig

SOURCE = "conditioner_gain"
SCALED = ("S", "S_times_M")  # the results proportional to S (S_dyn is scaled by the content)


@dataclass(frozen=True)
class CalibratedItem:
    """kind 'chain' | 'transducer'; scale: S_item = scale S_chain (S_chain in V/N); unit of S (and
    s_m_unit of S M); rel_std: the conditioner's relative standard uncertainty entering S (0 for a
    chain); title and text for the certificate; conditioner: what it states of the conditioner."""

    kind: str
    scale: float
    unit: str
    s_m_unit: str
    rel_std: float
    title: str
    text: str
    conditioner: dict[str, Any]

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "scale": self.scale, "unit": self.unit, "rel_std": self.rel_std,
                "title": self.title, "text": self.text, "conditioner": self.conditioner}


def calibrated_item(config: Mapping[str, Any] | None) -> CalibratedItem:
    """The item of a recording's configuration snapshot (its ``conditioner`` section)."""
    raw = (config or {}).get("conditioner") if isinstance(config, Mapping) else None
    c = ConditionerConfig.model_validate(raw or {})
    gain = f"gain {c.gain:g} {c.gain_unit}"
    if c.calibrated == "chain":
        return CalibratedItem("chain", 1.0, "V/N", "V*s^2/m", 0.0,
                              "Calibration certificate for a force measuring chain",
                              f"force measuring chain: the transducer with its conditioner ({gain}), calibrated "
                              "as one chain; S is the sensitivity of the chain (conditioner gain included)",
                              {"gain": c.gain, "gain_unit": c.gain_unit, "role": "part of the item calibrated"})
    rel = float(math.hypot(c.gain_rel_std or 0.0, c.excitation_rel_std or 0.0))
    stated = {"gain": c.gain, "gain_unit": c.gain_unit, "gain_rel_std": c.gain_rel_std,
              "excitation_V": c.excitation_V, "excitation_rel_std": c.excitation_rel_std,
              "role": "calibrated reference standard (not part of the item)"}
    if c.gain_unit == "V/pC":
        return CalibratedItem("transducer", 1.0 / c.gain, "pC/N", "pC*s^2/m", rel,
                              "Calibration certificate for a force transducer",
                              f"force transducer (piezoelectric) alone; measured through a reference charge "
                              f"amplifier of {gain} (relative standard uncertainty {c.gain_rel_std:.2g})",
                              stated)
    if c.excitation_V is None:
        return CalibratedItem("transducer", 1.0 / c.gain, "V/N", "V*s^2/m", rel,
                              "Calibration certificate for a force transducer",
                              f"force transducer alone (bridge output per newton); measured through a reference "
                              f"conditioner of {gain} (relative standard uncertainty {c.gain_rel_std:.2g})",
                              stated)
    return CalibratedItem("transducer", 1e3 / (c.gain * c.excitation_V), "mV/V/N", "mV/V*s^2/m", rel,
                          "Calibration certificate for a force transducer",
                          f"force transducer alone (strain-gauge bridge, S in mV/V per newton); measured through a "
                          f"reference conditioner of {gain} (relative standard uncertainty {c.gain_rel_std:.2g}) "
                          f"at a bridge excitation of {c.excitation_V:g} V (relative standard uncertainty "
                          f"{c.excitation_rel_std:.2g})", stated)


def _scaled_entry(entry: Mapping[str, Any], value: float, item: CalibratedItem, unit: str) -> dict[str, Any]:
    """A budget entry of a quantity proportional to S in the item's unit, with the conditioner's term."""
    contributions = {s: (None if u is None else item.scale * float(u))
                     for s, u in (entry.get("contributions") or {}).items()}
    combined = abs(item.scale) * float(entry.get("combined") or 0.0)
    if item.kind == "transducer":
        u_cond = abs(item.scale * value) * item.rel_std
        contributions[SOURCE] = u_cond
        combined = math.hypot(combined, u_cond)
    return {**entry, "contributions": contributions, "combined": combined, "unit": unit}


def item_budget(budget: Mapping[str, Mapping[str, Any]], values: Mapping[str, float | None],
                item: CalibratedItem) -> dict[str, dict[str, Any]]:
    """The stored budget (``{parameter: entry}``, S in V/N) as the item's: S rescaled with the
    conditioner's term; the others unchanged but for a zero ``conditioner_gain`` column."""
    out: dict[str, dict[str, Any]] = {}
    for name, entry in budget.items():
        v = values.get(name)
        if name in SCALED and v is not None:
            out[name] = _scaled_entry(entry, float(v), item, item.unit if name == "S" else item.s_m_unit)
        else:
            out[name] = {**entry, "contributions": {**(entry.get("contributions") or {}),
                                                    **({SOURCE: 0.0} if item.kind == "transducer" else {})}}
    return out


def scaled_determined(q: Mapping[str, Any], name: str, item: CalibratedItem) -> dict[str, Any]:
    """A ``determined`` entry (value, unit, combined, one key per source) in the item's unit."""
    if name not in SCALED or q.get("value") is None:
        return dict(q)
    sources = {k: v for k, v in q.items() if k not in ("value", "unit", "combined", "note")}
    entry = _scaled_entry({"contributions": sources, "combined": q.get("combined")}, float(q["value"]), item,
                          item.s_m_unit)
    return {**q, **entry["contributions"], "value": item.scale * float(q["value"]), "combined": entry["combined"],
            "unit": entry["unit"]}
