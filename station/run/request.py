"""A calibration run request and its validation against the rig and transducer limits."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

from station.config import (
    MAX_METHODS,
    MAX_STEPS,
    MAX_TOP_MASS_KG,
    EnvironmentConfig,
    MethodChoice,
    StationConfig,
    StepSpec,
    check_method_list,
    number_only,
)
from station.errors import LimitError
from station.limits import check_drive, check_steps, max_radius_m


class RunRequest(BaseModel):
    """What a technician or the nightly batch asks the rig to do."""

    model_config = ConfigDict(extra="forbid")

    transducer_id: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.\-]+$")
    top_mass_kg: float = Field(gt=0, le=MAX_TOP_MASS_KG, description="top mass in kg (without the adaption)")
    steps: list[StepSpec] = Field(min_length=1, max_length=MAX_STEPS)
    methods: list[MethodChoice] | None = Field(
        default=None, min_length=1, max_length=MAX_METHODS,
        description="this run's identifications, ordered, the first being the primary result (default: the "
        "configuration's identification.methods)")
    standards: list[str] | None = Field(default=None, max_length=32, description="ids of the reference "
                                        "standards used (register); default: those marked in use")
    environment: EnvironmentConfig | None = Field(
        default=None, description="air temperature (degC) and relative humidity (%) during the run, entered by the "
        "technician; stored in the recording's start document and stated on the certificate (default: the "
        "configuration's environment, or the simulated rig's room sensor)")

    @field_validator("top_mass_kg", mode="before")
    @classmethod
    def _a_number(cls, v: object) -> object:
        return number_only(v)

    @field_validator("methods")
    @classmethod
    def _methods(cls, v: list[MethodChoice] | None) -> list[MethodChoice] | None:
        return None if v is None else check_method_list(v)


@dataclass(frozen=True)
class PlannedStep:
    """A validated step with every time filled in (Hz, m, s)."""

    index: int
    crank_frequency_hz: float
    crank_radius_m: float
    settle_s: float
    record_s: float


@dataclass(frozen=True)
class Plan:
    """A run that passed every limit check: the effective configuration and its steps."""

    config: StationConfig
    steps: tuple[PlannedStep, ...]
    provenance: dict[str, Any] = field(default_factory=dict)  # who, the register's records (station.lab)

    def to_dict(self) -> dict[str, object]:
        return {"kind": "stepped_sine", "transducer_id": self.config.transducer.id,
                "top_mass_kg": self.config.rig.top_mass_kg,
                "steps": [s.__dict__ for s in self.steps],
                "units": {"crank_frequency_hz": "Hz", "crank_radius_m": "m", "settle_s": "s",
                          "record_s": "s", "top_mass_kg": "kg"},
                **({"provenance": self.provenance} if self.provenance else {})}


def plan_run(cfg: StationConfig, request: RunRequest) -> Plan:
    """Check a request before anything moves; raises :class:`LimitError` naming the offending step,
    field, value and limit (once: callers map it, e.g. the API to a 422 at that field), also where
    the configuration asks the drive for more than its profile declares (``check_drive``)."""
    if request.transducer_id != cfg.transducer.id:
        raise LimitError(f"transducer_id {request.transducer_id!r} is not the one mounted on this station "
                         f"({cfg.transducer.id!r}, from the configuration)", field="transducer_id",
                         value=request.transducer_id, limit=cfg.transducer.id)
    eff = cfg.model_copy(update={"rig": cfg.rig.model_copy(update={"top_mass_kg": request.top_mass_kg})})
    if request.environment is not None:  # the recording's start document takes it (station.environment)
        eff = eff.model_copy(update={"environment": request.environment})
    if request.methods is not None:  # stored with the recording's configuration: the worker reads it there
        eff = eff.model_copy(update={"identification": eff.identification.model_copy(
            update={"methods": list(request.methods)})})
    check_steps(eff, request.steps)
    check_drive(eff, request.steps)
    steps = tuple(
        PlannedStep(i, s.crank_frequency_hz, s.crank_radius_m,
                    cfg.plan.settle_s if s.settle_s is None else s.settle_s,
                    cfg.plan.record_s if s.record_s is None else s.record_s)
        for i, s in enumerate(request.steps))
    return Plan(eff, steps)


def default_request(cfg: StationConfig, frequencies_hz: list[float] | None = None) -> RunRequest:
    """The configured plan as a request; with ``frequencies_hz``, the largest radius within the
    limits (capped by the plan's first radius) is chosen for each frequency."""
    if not frequencies_hz:
        return RunRequest(transducer_id=cfg.transducer.id, top_mass_kg=cfg.rig.top_mass_kg,
                          steps=list(cfg.plan.steps))
    r_cap = min(cfg.plan.steps[0].crank_radius_m, cfg.rig.crank_radius_m.max)
    steps = []
    fr = cfg.rig.crank_frequency_hz
    for i, f in enumerate(frequencies_hz):
        if not fr.contains(f):
            raise LimitError(f"{f:g} Hz: outside the rig's crank frequency range [{fr.min:g}, {fr.max:g}] Hz "
                             "(rig.crank_frequency_hz)", step=i, field="crank_frequency_hz", value=f,
                             limit=(fr.min, fr.max))
        r = min(r_cap, 0.9 * max_radius_m(cfg, f))  # 10 % margin below the force limit
        if r < cfg.rig.crank_radius_m.min:
            raise LimitError(f"{f:g} Hz: no crank radius within [{cfg.rig.crank_radius_m.min:g}, "
                             f"{cfg.rig.crank_radius_m.max:g}] m keeps the peak force within the limit",
                             step=i, field="crank_frequency_hz", value=f, limit=max_radius_m(cfg, f))
        steps.append(StepSpec(crank_frequency_hz=f, crank_radius_m=float(f"{r:.3g}")))
    return RunRequest(transducer_id=cfg.transducer.id, top_mass_kg=cfg.rig.top_mass_kg, steps=steps)
