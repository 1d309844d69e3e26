"""What an identification takes from outside the data: the masses and the measurement chain.

* **End mass m_e** (kg): from the station configuration (``transducer.end_mass_kg``, source
  ``config``) or an imported run's RUN.yaml (``end_mass_kg``, source ``recording``), each with its
  standard uncertainty (``end_mass_std_kg``; default ``DEFAULT_END_MASS_REL_STD`` of the value, a
  data-sheet figure).  Not given: the data determine only S (m_l + m_e), k_f / (m_l + m_e) and
  b_f / (m_l + m_e); S, k_f, b_f are then *conditional* on an assumed end mass (0 kg unless the
  caller assumes another value), source ``assumed``, and every output says so.
* **Load mass m_l** (kg, top mass + adaption): weighed; standard uncertainty ``load_mass_std_kg``
  (station configuration ``rig.load_mass_std_kg``, RUN.yaml ``top_mass_std_kg``), default
  ``DEFAULT_LOAD_MASS_REL_STD`` of the value.
* **Measurement chain** (``station.config.MeasurementChain``): what the conditioner, the DAQ and the displacement
  sensor get wrong, as standard uncertainties of H(f).  Station configuration
  ``identification.chain``, RUN.yaml ``measurement_chain``; defaults documented per field.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pydantic import ValidationError

from station.config import MeasurementChain
from station.errors import BadInputError
from station.ident.models import Model, make_model

DEFAULT_END_MASS_REL_STD = 0.05
DEFAULT_LOAD_MASS_REL_STD = 1e-4
DEFAULT_CRANK_RADIUS_STD_M = 1e-7  # a motorised eccentric read by its encoder



@dataclass(frozen=True)
class MassInput:
    """A mass in kg with its standard uncertainty; value None = not given.  source: config,
    recording or assumed."""

    value: float | None
    std: float | None
    source: str

    def to_dict(self) -> dict[str, Any]:
        return {"value": self.value, "std": self.std, "source": self.source}


@dataclass(frozen=True)
class IdentInputs:
    """Masses and chain for one identification.  end_mass.source == 'assumed' with std None means
    S, k_f, b_f are conditional on end_mass.value (no uncertainty is propagated for it)."""

    end_mass: MassInput
    load_mass: MassInput
    chain: MeasurementChain
    end_mass_given: bool
    crank_radius_std_m: float = DEFAULT_CRANK_RADIUS_STD_M
    defaults: tuple[str, ...] = ()  # the standard uncertainties used that no certificate supports (defaults)

    @property
    def m_e(self) -> float:
        return float(self.end_mass.value or 0.0)

    @property
    def m_l(self) -> float:
        return float(self.load_mass.value or 0.0)

    def to_dict(self) -> dict[str, Any]:
        """The ``assumptions`` of the result JSON."""
        return {"end_mass_kg": self.end_mass.to_dict(), "load_mass_kg": self.load_mass.to_dict(),
                "measurement_chain": self.chain.model_dump(),
                "displacement_chain": self.chain.displacement_statement(),
                "crank_radius_std_m": self.crank_radius_std_m,
                "unsupported_defaults": list(self.defaults)}


def _num(d: Any, *keys: str) -> float | None:
    for k in keys:
        if not isinstance(d, dict):
            return None
        d = d.get(k)
    return float(d) if isinstance(d, int | float) and not isinstance(d, bool) else None


def inputs_for(rec: Any, *, assumed_end_mass_kg: float | None = None,
               assumed_end_mass_std_kg: float | None = None,
               chain: MeasurementChain | None = None) -> IdentInputs:
    """Masses and chain of a recording (``station.recording.Recording``).

    assumed_end_mass_kg: used only when the recording gives no end mass; the results are then
    conditional on it, unless assumed_end_mass_std_kg states its standard uncertainty (then it is
    propagated like a given one, source still 'assumed')."""
    cfg = rec.config if isinstance(rec.config, dict) else {}
    imported = cfg.get("format") == "sinecal-csv"
    src = "recording" if imported else "config"
    m_l = float(rec.load_mass_kg)
    u_l = _num(cfg, "top_mass_std_kg") if imported else _num(cfg, "rig", "load_mass_std_kg")
    load = MassInput(m_l, u_l if u_l is not None else DEFAULT_LOAD_MASS_REL_STD * m_l, src)
    defaults = [] if u_l is not None else [f"load mass u = {DEFAULT_LOAD_MASS_REL_STD:g} of its value"]
    u_r = _num(cfg, "rig", "crank_radius_std_m")
    if u_r is None:
        defaults.append(f"crank radius u = {DEFAULT_CRANK_RADIUS_STD_M:g} m")
    if rec.end_mass_kg is not None:
        u_e = _num(cfg, "end_mass_std_kg") if imported else _num(cfg, "transducer", "end_mass_std_kg")
        end = MassInput(float(rec.end_mass_kg), u_e if u_e is not None
                        else DEFAULT_END_MASS_REL_STD * float(rec.end_mass_kg), src)
        given = True
        if u_e is None:
            defaults.append(f"end mass u = {DEFAULT_END_MASS_REL_STD:g} of its value")
    else:
        given = assumed_end_mass_kg is not None and assumed_end_mass_std_kg is not None
        end = MassInput(float(assumed_end_mass_kg or 0.0), assumed_end_mass_std_kg if given else None, "assumed")
    if chain is None:
        raw = cfg.get("measurement_chain") if imported else (cfg.get("identification") or {}).get("chain")
        try:
            chain = MeasurementChain.model_validate(raw or {})
        except ValidationError as exc:
            raise BadInputError(f"{rec.path}: measurement chain: {exc.errors()[0]['msg']} "
                                f"(received {raw!r})") from None
    if chain.gain_rel_std == MeasurementChain.model_fields["gain_rel_std"].default:  # a snapshot states defaults too
        defaults.append(f"measurement chain gain u = {chain.gain_rel_std:g} (relative)")
    return IdentInputs(end, load, chain, given, DEFAULT_CRANK_RADIUS_STD_M if u_r is None else u_r,
                       tuple(defaults))


def model_for(rec: Any, key: str, inputs: IdentInputs | None = None) -> Model:
    """The model with the recording's masses (m_l load mass, m_e end mass; an unknown end mass is
    the assumed one of ``inputs``, 0 by default, and the result is then conditional on it)."""
    inputs = inputs or inputs_for(rec)
    if not inputs.end_mass_given and key in ("coupled", "h1"):
        raise BadInputError(f"{rec.path}: the coupled model needs the end mass, which is not recorded")
    return make_model(key, inputs.m_e, inputs.m_l)
