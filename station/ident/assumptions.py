"""What a result rests on beyond its data, as frozen types: the masses, the measurement chain, the
model structure and the estimator's own conditions (the result's ``assumptions``).

JSON (as stored beside a recording and served by the API): ``{"end_mass_kg": {value, std, source},
"load_mass_kg": {...}, "measurement_chain": {...}, "displacement_chain": {...}, "crank_radius_std_m",
"unsupported_defaults": [...], "structure": {model, equation, displacement_chain[, coupling]}[,
"rls_uncertainty": {...}]}``; a campaign's (``CampaignAssumptions``) states every recording's load
mass and the joint model instead.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from station.ident.inputs import IdentInputs, MassInput
from station.jsonvalue import JsonValue

_COUPLING_FIELDS = ("assumed", "data_determine", "contradicted_by_the_data")


def _mass(d: object) -> MassInput | None:
    if not isinstance(d, Mapping):
        return None
    v, s = d.get("value"), d.get("std")
    return MassInput(None if v is None else float(v), None if s is None else float(s), str(d.get("source") or ""))


@dataclass(frozen=True)
class CouplingStatement:
    """The stiff-coupling assumption of an Eq. 9 result: what the data determine instead of k_f, the
    numbers of the couplings this plan cannot tell from a stiff one (``structure.CouplingBound``'s,
    empty when not tested) and whether the data contradict it."""

    data_determine: str
    bound: Mapping[str, JsonValue] = field(default_factory=dict)
    contradicted_by_the_data: bool = False

    @property
    def k_f_alone_range(self) -> tuple[float, float | None] | None:
        """(k_s, high) in N/m of k_f alone under the couplings not excluded (high None: unbounded)."""
        rng = self.bound.get("k_f_alone_range_N_per_m")
        if not isinstance(rng, list | tuple) or len(rng) != 2 or not isinstance(rng[0], int | float) \
                or not (rng[1] is None or isinstance(rng[1], int | float)):
            return None
        return float(rng[0]), None if rng[1] is None else float(rng[1])

    def to_dict(self) -> dict[str, JsonValue]:
        out: dict[str, JsonValue] = {"assumed": "stiff", "data_determine": self.data_determine, **self.bound}
        if self.contradicted_by_the_data:
            out["contradicted_by_the_data"] = True
        return out


@dataclass(frozen=True)
class StructureStatement:
    """Which model a result rests on (``COUPLED`` or ``STIFF``, its equation), the displacement chain's
    response as the result states it, and the coupling assumption (None for the coupled model)."""

    model: str
    equation: str
    displacement_chain: Mapping[str, JsonValue]
    coupling: CouplingStatement | None = None

    def to_dict(self) -> dict[str, JsonValue]:
        out: dict[str, JsonValue] = {"model": self.model, "equation": self.equation,
                                  "displacement_chain": dict(self.displacement_chain)}
        if self.coupling is not None:
            out["coupling"] = self.coupling.to_dict()
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> StructureStatement:
        c = d.get("coupling")
        coupling = None if not isinstance(c, Mapping) else CouplingStatement(
            str(c.get("data_determine") or ""), {str(k): v for k, v in c.items() if k not in _COUPLING_FIELDS},
            bool(c.get("contradicted_by_the_data")))
        return cls(str(d.get("model") or ""), str(d.get("equation") or ""), dict(d.get("displacement_chain") or {}),
                   coupling)


@dataclass(frozen=True)
class Assumptions:
    """A recording's result's assumptions: end and load mass (kg, with standard uncertainty and
    source), the measurement chain as stated (``station.config.MeasurementChain`` fields) and its
    displacement response, the crank radius's standard uncertainty (m), the standard uncertainties
    used that no certificate supports, the model structure, and the RLS uncertainty's conditions
    (empty for the other estimators)."""

    end_mass: MassInput | None = None
    load_mass: MassInput | None = None
    measurement_chain: Mapping[str, JsonValue] = field(default_factory=dict)
    displacement_chain: Mapping[str, JsonValue] = field(default_factory=dict)
    crank_radius_std_m: float | None = None
    unsupported_defaults: tuple[str, ...] = ()
    structure: StructureStatement | None = None
    rls_uncertainty: Mapping[str, str] = field(default_factory=dict)

    @classmethod
    def of(cls, inputs: IdentInputs, structure: StructureStatement | None,
           rls_uncertainty: Mapping[str, str] | None = None) -> Assumptions:
        """The assumptions of a result identified from ``inputs`` on ``structure``."""
        return cls(inputs.end_mass, inputs.load_mass, inputs.chain.model_dump(), inputs.chain.displacement_statement(),
                   inputs.crank_radius_std_m, inputs.defaults, structure, dict(rls_uncertainty or {}))

    @property
    def mass_std_kg(self) -> float:
        """u(M) of M = m_e + m_l (0 for a mass without one)."""
        return math.hypot(*[float(m.std) if m is not None and m.std is not None else 0.0
                            for m in (self.end_mass, self.load_mass)])

    def to_dict(self) -> dict[str, JsonValue]:
        out: dict[str, JsonValue] = {}
        if self.end_mass is not None:
            out["end_mass_kg"] = self.end_mass.to_dict()
        if self.load_mass is not None:
            out["load_mass_kg"] = self.load_mass.to_dict()
        if self.measurement_chain:
            out["measurement_chain"] = dict(self.measurement_chain)
        if self.displacement_chain:
            out["displacement_chain"] = dict(self.displacement_chain)
        if self.crank_radius_std_m is not None:
            out["crank_radius_std_m"] = self.crank_radius_std_m
        if self.measurement_chain or self.unsupported_defaults:
            out["unsupported_defaults"] = list(self.unsupported_defaults)
        if self.structure is not None:
            out["structure"] = self.structure.to_dict()
        if self.rls_uncertainty:
            out["rls_uncertainty"] = dict(self.rls_uncertainty)
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> Assumptions:
        """Read back ``to_dict`` (keys a result was stored without are left empty)."""
        d = d or {}
        st, r = d.get("structure"), d.get("crank_radius_std_m")
        return cls(_mass(d.get("end_mass_kg")), _mass(d.get("load_mass_kg")), dict(d.get("measurement_chain") or {}),
                   dict(d.get("displacement_chain") or {}), None if r is None else float(r),
                   tuple(str(x) for x in d.get("unsupported_defaults") or ()),
                   StructureStatement.from_dict(st) if isinstance(st, Mapping) else None,
                   {str(k): str(v) for k, v in (d.get("rls_uncertainty") or {}).items()})


@dataclass(frozen=True)
class RunMass:
    """A campaign recording's load mass as weighed: run id, value and standard uncertainty (kg)."""

    run_id: str
    value: float
    std: float


@dataclass(frozen=True)
class CampaignAssumptions:
    """A campaign's assumptions: the joint model, the end mass (determined by the campaign, stated or
    assumed; None when refused without one), every recording's load mass, the shared measurement
    chain as stated and the structure the joint fit rests on."""

    model: str
    end_mass: MassInput | None
    load_masses: tuple[RunMass, ...]
    measurement_chain: Mapping[str, JsonValue]
    structure: StructureStatement

    def to_dict(self) -> dict[str, JsonValue]:
        return {"model": self.model, "end_mass_kg": None if self.end_mass is None else self.end_mass.to_dict(),
                "load_mass_kg": [{"run_id": m.run_id, "value": m.value, "std": m.std} for m in self.load_masses],
                "measurement_chain": dict(self.measurement_chain), "structure": self.structure.to_dict()}
