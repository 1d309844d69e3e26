"""What a run's reference standards put into its uncertainty budget.

The register's standards carry the standard uncertainty their calibration certificates state
(``Standard.uncertainty`` in ``uncertainty_unit``).  A run takes them into the configuration it
records, so the identification's budget rests on the certificates, not on the station's defaults:

* ``masses`` in kg: the load mass's standard uncertainty (``rig.load_mass_std_kg``); ``relative``:
  that fraction of the load mass;
* ``displacement_sensor`` and ``daq`` as ``relative``: the gain ratio of the force and displacement
  chains (``identification.chain.gain_rel_std``, their root sum of squares);
* ``conditioner`` as ``relative``: the reference conditioner's gain (``conditioner.gain_rel_std``)
  when the transducer alone is calibrated; as part of a calibrated chain it is in the item's S.

Any other unit (e.g. a displacement sensor's uncertainty in m) is stated with the standard but enters
no budget term; ``use`` says which, in words, for the certificate.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

from station.config import StationConfig


def use(standard: Mapping[str, Any], load_mass_kg: float, reference_conditioner: bool) -> tuple[str, float] | None:
    """(configuration field, value) a standard sets, or None when it enters no budget term;
    load_mass_kg: the run's top + adaption mass; reference_conditioner: the transducer alone is
    calibrated (``conditioner.calibrated: transducer``)."""
    kind, unit, u = standard.get("kind"), standard.get("uncertainty_unit"), standard.get("uncertainty")
    if not isinstance(u, int | float) or isinstance(u, bool):
        return None
    if kind == "masses" and unit == "kg":
        return "rig.load_mass_std_kg", float(u)
    if kind == "masses" and unit == "relative":
        return "rig.load_mass_std_kg", float(u) * load_mass_kg
    if kind in ("displacement_sensor", "daq") and unit == "relative":
        return "identification.chain.gain_rel_std", float(u)
    if kind == "conditioner" and unit == "relative" and reference_conditioner:
        return "conditioner.gain_rel_std", float(u)
    return None


USE_TEXT = {"rig.load_mass_std_kg": "the load mass's standard uncertainty",
            "identification.chain.gain_rel_std": "the gain ratio of the force and displacement chains",
            "conditioner.gain_rel_std": "the reference conditioner's gain"}


def use_text(standard: Mapping[str, Any], load_mass_kg: float, reference_conditioner: bool) -> str:
    """How the certificate says what a standard's uncertainty does in the budget (``use``)."""
    u = use(standard, load_mass_kg, reference_conditioner)
    if u is None:
        return "stated; enters no budget term (its unit has no term)"
    return f"in the budget as {USE_TEXT[u[0]]}"


def with_standards(cfg: StationConfig, standards: Iterable[Mapping[str, Any]]) -> StationConfig:
    """The configuration with the uncertainties the standards' certificates state in place of the
    station's defaults (module docstring); unchanged without standards."""
    fields: dict[str, list[float]] = {}
    for s in standards:
        u = use(s, cfg.rig.load_mass_kg, cfg.conditioner.calibrated == "transducer")
        if u is not None:
            fields.setdefault(u[0], []).append(u[1])
    if not fields:
        return cfg
    d = cfg.model_dump(mode="json")
    for key, values in fields.items():
        section, *path, name = key.split(".")
        target = d[section]
        for p in path:
            target = target.setdefault(p, {})
        target[name] = math.sqrt(sum(v * v for v in values))
    return StationConfig.model_validate(d)
