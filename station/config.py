"""Station configuration: YAML files in ``config/`` loaded into strict pydantic models.

Unknown keys and out-of-range values are refused with a message naming the key, the value received
and the allowed range.  All quantities are SI; the unit is part of every field name.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
from pathlib import Path
from typing import Annotated, Any, Literal, get_type_hints

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_core import ErrorDetails
from sinecal_config import config_file

from drivers.daq.protocol import link_budget
from drivers.rig import params as rp
from station.bounded import MAX_YAML_BYTES, load_yaml, quote, read_text_limited
from station.errors import ConfigError
from station.vocabulary import MODELS_OF_METHOD, Method

# inf and nan are refused everywhere: several fields (e.g. Range.max, mains amplitudes) have no
# upper bound that would catch them.
_STRICT = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

Pos = Annotated[float, Field(gt=0)]

# Bounds of every configuration, run request and the limits the daemon publishes (GET /station).
MAX_TOP_MASS_KG = 500.0
MAX_CRANK_FREQUENCY_HZ = 1000  # a step's crank frequency, wherever a step is declared
MAX_CRANK_RADIUS_M = 1.0
MAX_STEPS = 200

# a step's quantities with their bounds, declared once for every step type (the configuration's plan,
# the run request, the interchange file and the API's schemas built from them)
CrankFrequencyHz = Annotated[float, Field(gt=0, le=MAX_CRANK_FREQUENCY_HZ)]
CrankRadiusM = Annotated[float, Field(gt=0, le=MAX_CRANK_RADIUS_M)]
SettleS = Annotated[float, Field(ge=0, le=600)]
RecordS = Annotated[float, Field(gt=0, le=3600)]

DEFAULT_RESONANCE_REL_STD = 0.05  # u(f_r) of a displacement resonance stated without one, relative


class MeasurementChain(BaseModel):
    """Standard uncertainties of the measured H(f) that the noise does not show.

    gain_rel_std: ratio of the force chain's to the displacement chain's gain (conditioner, ADC,
    displacement sensor), the same at every frequency (correlated), relative;
    flatness_rel_std: gain error independent from one frequency to the next, relative;
    phase_offset_std_deg: constant phase offset between the channels (correlated), deg;
    phase_std_deg: phase error independent from one frequency to the next, deg;
    delay_std_s: time skew between the channels (phase 2 pi f tau, correlated across frequencies), s;
    displacement_resonance_hz: the displacement sensor's own resonance f_r in Hz (its response
    w_r^2 / (w_r^2 - w^2 + 2 j p w_r w), ``drivers.rig.params.DisplacementResonance``), None (the
    default) for a flat displacement chain (its deviations within the flatness and phase terms);
    when given, H(f) is corrected for it and its uncertainty enters the budget;
    displacement_resonance_std_hz: standard uncertainty of f_r, Hz (default 5 % of f_r);
    displacement_damping: the resonance's damping ratio p; displacement_damping_std: its standard
    uncertainty (default 0.1).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    gain_rel_std: float = Field(default=1e-4, ge=0, le=0.5)
    flatness_rel_std: float = Field(default=5e-5, ge=0, le=0.5)
    phase_offset_std_deg: float = Field(default=0.005, ge=0, le=10)
    phase_std_deg: float = Field(default=0.005, ge=0, le=10)
    delay_std_s: float = Field(default=1e-7, ge=0, le=1e-2)
    displacement_resonance_hz: float | None = Field(default=None, gt=0, le=1e6)
    displacement_resonance_std_hz: float | None = Field(default=None, ge=0, le=1e6)
    displacement_damping: float = Field(default=0.0, ge=0, le=10)
    displacement_damping_std: float = Field(default=0.1, ge=0, le=10)

    @property
    def displacement_resonance(self) -> rp.DisplacementResonance | None:
        """The configured resonance of the displacement sensor, None for a flat chain."""
        if self.displacement_resonance_hz is None:
            return None
        return rp.DisplacementResonance(self.displacement_resonance_hz, self.displacement_damping)

    @property
    def resonance_std_hz(self) -> float:
        """u(f_r) in Hz: as stated, else 5 % of f_r (0 for a flat chain)."""
        if self.displacement_resonance_hz is None:
            return 0.0
        if self.displacement_resonance_std_hz is not None:
            return float(self.displacement_resonance_std_hz)
        return DEFAULT_RESONANCE_REL_STD * float(self.displacement_resonance_hz)

    def displacement_statement(self) -> dict[str, Any]:
        """The displacement chain's response as the result states it."""
        if self.displacement_resonance_hz is None:
            return {"response": "flat", "note": "the displacement chain is taken as flat: its gain and phase "
                    "errors within flatness_rel_std and phase_std_deg at every frequency of the plan"}
        return {"response": "resonance", "resonance_hz": self.displacement_resonance_hz,
                "resonance_std_hz": self.resonance_std_hz, "damping": self.displacement_damping,
                "damping_std": self.displacement_damping_std,
                "note": "H(f) corrected for the displacement sensor's resonance w_r^2 / (w_r^2 - w^2 + 2 j p w_r w); "
                        "its uncertainty is the budget's chain_resonance term"}

    @property
    def floor_gain(self) -> float:
        """Per-frequency relative gain floor (correlated and independent parts together)."""
        return float(np.hypot(self.gain_rel_std, self.flatness_rel_std))

    @property
    def floor_phase_rad(self) -> float:
        """Per-frequency phase floor without the delay, rad."""
        return float(np.deg2rad(np.hypot(self.phase_offset_std_deg, self.phase_std_deg)))

class _Model(BaseModel):
    model_config = _STRICT


def number_only(v: object) -> object:
    """Numbers only: ``true`` or ``"10"`` are not a frequency (pydantic would convert them)."""
    if isinstance(v, bool | str | bytes):
        raise ValueError(f"a number expected, got {type(v).__name__} {v!r}")
    return v


class Range(_Model):
    """A closed interval [min, max] of a quantity."""

    min: float = Field(ge=0)
    max: float = Field(gt=0)

    @model_validator(mode="after")
    def _ordered(self) -> Range:
        if self.min > self.max:
            raise ValueError(f"min ({self.min}) must not exceed max ({self.max})")
        return self

    def contains(self, value: float) -> bool:
        return self.min <= value <= self.max


class StationSection(_Model):
    """Where the station keeps its data."""

    name: str = "sinecal"
    recordings_dir: str = "recordings"
    min_free_mb: float = Field(default=64.0, ge=0, le=1e6, description="free disk space kept in reserve; "
                               "a run stops before it would be used")


class TransducerConfig(_Model):
    """The transducer under calibration (nominal data from its data sheet)."""

    id: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.\-]+$")
    capacity_N: float = Field(gt=0, le=1e7)
    sensitivity_V_per_N: float = Field(gt=0, le=1.0, description="bridge output per N")
    end_mass_kg: float | None = Field(default=None, gt=0, le=100)
    end_mass_std_kg: float | None = Field(default=None, ge=0, le=100, description="standard uncertainty "
                                          "of end_mass_kg (default: 5 % of it, station.ident.inputs)")
    type: str = Field(default="", max_length=128, description="make and model")
    serial: str = Field(default="", max_length=128, description="serial number")
    owner: str = Field(default="", max_length=256, description="owner or customer")


class MotorSection(_Model):
    """The crank drive: which drive profile describes it (``docs/drive-profiles.md``)."""

    profile: str = Field(default="sinecal-crank", min_length=1, max_length=4096,
                         description="a shipped drive profile by name (config/drives/<name>.yaml) or the "
                         "path of a profile YAML")


class RigConfig(_Model):
    """The sine-mechanism rig and its limits."""

    motor: MotorSection = MotorSection()

    top_mass_kg: float = Field(gt=0, le=MAX_TOP_MASS_KG)
    adaption_mass_kg: float = Field(default=0.0, ge=0, le=100)
    load_mass_std_kg: float | None = Field(default=None, ge=0, le=100, description="standard uncertainty "
                                           "of top + adaption mass (default: 1e-4 of it)")
    crank_radius_m: Range = Range(min=1e-4, max=0.05)
    crank_radius_std_m: float | None = Field(default=None, ge=0, le=0.01, description="standard uncertainty "
                                             "of a set crank radius in m (default: 1e-7 m, which no certificate "
                                             "supports); the measured displacement amplitude is checked against it")
    crank_frequency_hz: Range = Range(min=1.0, max=100.0)
    peak_force_fraction: float = Field(default=0.8, gt=0, le=1.0,
                                       description="peak force limit as a fraction of capacity")
    acceleration_hz_per_s: float = Field(default=10.0, gt=0, le=200.0,
                                         description="crank-frequency ramp rate in Hz/s; a run is refused "
                                         "when it is planned unless the drive profile's ramp register takes "
                                         "it (sinecal-crank: 0.01..100 Hz/s; docs/drive-profiles.md)")

    @property
    def load_mass_kg(self) -> float:
        """m_l of paper Eq. 3: top mass plus adaption."""
        return self.top_mass_kg + self.adaption_mass_kg


class ConditionerConfig(_Model):
    """The conditioner between the transducer and the DAQ, and what a certificate calibrates.

    calibrated: ``chain``, the transducer and this conditioner are calibrated as one measuring chain
    (S in V/N with the gain inside); ``transducer``, the conditioner is a calibrated reference
    standard and S is the transducer's own (gain_unit V/V with excitation_V: mV/V per N of a bridge;
    V/V alone: V/N of the bridge output; V/pC: pC/N of a piezo transducer), its gain's (and the
    excitation's) stated uncertainty entering the budget of S (``station.certificate.item``)."""

    gain: float = Field(default=1000.0, gt=0, le=1e6, description="V/V (or V/pC, gain_unit)")
    offset_V: float = Field(default=0.0, ge=-10, le=10)
    calibrated: Literal["chain", "transducer"] = Field(
        default="chain", description="chain: transducer and conditioner calibrated as one chain; transducer: "
        "the conditioner is a calibrated reference, S is the transducer's alone")
    gain_unit: Literal["V/V", "V/pC"] = "V/V"
    gain_rel_std: float | None = Field(default=None, ge=0, le=0.5, description="relative standard "
                                       "uncertainty of gain from the conditioner's certificate (needed when "
                                       "calibrated is transducer)")
    excitation_V: float | None = Field(default=None, gt=0, le=100, description="bridge excitation, V")
    excitation_rel_std: float | None = Field(default=None, ge=0, le=0.5, description="relative standard "
                                             "uncertainty of excitation_V (needed with it)")

    @model_validator(mode="after")
    def _reference_stated(self) -> ConditionerConfig:
        if self.calibrated == "transducer":
            if self.gain_rel_std is None:
                raise ValueError("a reference conditioner (calibrated: transducer) needs gain_rel_std, the "
                                 "relative standard uncertainty of its gain from its certificate")
            if self.excitation_V is not None and self.excitation_rel_std is None:
                raise ValueError("excitation_V needs excitation_rel_std, its relative standard uncertainty")
            if self.excitation_V is not None and self.gain_unit != "V/V":
                raise ValueError("excitation_V is a bridge's: it needs gain_unit V/V")
        return self


class DisplacementSensorConfig(_Model):
    gain_V_per_m: float = Field(default=500.0, gt=0, le=1e6)


class DaqConfig(_Model):
    sample_rate_hz: float = Field(default=20_000.0, ge=1000, le=200_000)
    adc_bits: int = Field(default=16, ge=8, le=16)
    displacement_range_V: float = Field(default=10.0, gt=0, le=10)
    force_range_V: float = Field(default=10.0, gt=0, le=10)


class StepSpec(_Model):
    """One step of a stepped-sine run, as the configuration's plan, a run request (the API's and the
    CLI's) and a proposal state it; settle and record times default to the plan's."""

    crank_frequency_hz: CrankFrequencyHz = Field(description="crank frequency in Hz")
    crank_radius_m: CrankRadiusM = Field(description="crank radius in m")
    settle_s: SettleS | None = Field(default=None, description="settling time in s")
    record_s: RecordS | None = Field(default=None, description="record time in s")

    @field_validator("crank_frequency_hz", "crank_radius_m", "settle_s", "record_s", mode="before")
    @classmethod
    def _a_number(cls, v: object) -> object:
        return number_only(v)


class PlanConfig(_Model):
    """The default run: steps with settle and record times."""

    settle_s: SettleS = 1.0
    record_s: RecordS = 2.0
    steps: list[StepSpec] = Field(min_length=1, max_length=MAX_STEPS)


class TruthConfig(_Model):
    """True mechanical parameters of the simulated transducer."""

    k_f: float = Field(gt=0, le=1e12, description="N/m")
    b_f: float = Field(ge=0, le=1e8, description="N*s/m")
    end_mass_kg: float | None = Field(default=None, gt=0, le=100,
                                      description="true end mass; defaults to the transducer's")
    sensitivity_V_per_N: float | None = Field(default=None, gt=0, le=1.0,
                                              description="true sensitivity; defaults to nominal")
    load_mass_kg: float | None = Field(default=None, gt=0, le=MAX_TOP_MASS_KG + 100,
                                       description="true load mass (top + adaption); defaults to the stated one")
    displacement_gain_V_per_m: float | None = Field(default=None, gt=0, le=1e6, description="true gain of the "
                                                    "displacement sensor; defaults to the stated one")


class SimulationConfig(_Model):
    """The simulated rig: truth, noise, effects, seed."""

    seed: int = Field(default=1, ge=0)
    truth: TruthConfig
    displacement_noise_m: float = Field(default=2e-7, ge=0, le=1e-2)
    conditioner_noise_V: float = Field(default=5e-4, ge=0, le=1.0)
    pre_roll_s: float = Field(default=0.5, ge=0, le=60, description="standstill before the first ramp")
    effects: rp.Effects = Field(default=rp.Effects(), description="the simulator's effect catalogue "
                                "(drivers.rig.params.Effects, bounds declared there); an absent key is off")
    room_temperature_c: float = Field(default=20.0, ge=-40, le=80, description="the simulated room "
                                      "sensor's mean reading")
    room_humidity_pct: float = Field(default=45.0, ge=0, le=100)
    password_cost_log2: int = Field(default=14, ge=10, le=14, description="scrypt cost of the passwords the "
                                    "simulated station stores (N = 2**this; a check uses the cost stored "
                                    "with the hash): lower for demonstrations and tests, whose users are "
                                    "made and logged in often; a real rig's station always stores 2**14")


class DevicesConfig(_Model):
    """Where the real rig's devices are (ignored with --sim, which starts the emulators)."""

    motor_url: str = Field(default="modbus-tcp://127.0.0.1:502",
                           pattern=r"^modbus-(tcp|rtu)://.+", description="modbus-tcp://HOST:PORT or "
                           "modbus-rtu:///dev/ttyX?baudrate=115200")
    motor_device_id: int | None = Field(default=None, ge=1, le=247,
                                        description="Modbus unit id (default: the drive profile's)")
    daq_port: str = Field(default="/dev/ttyACM0", min_length=1)
    daq_link: Literal["uart", "usb-cdc"] = Field(
        default="uart", description="uart: the baud rate bounds the stream (checked here); usb-cdc: the "
        "bridge's own USB port, checked at connect against the throughput the bridge reports")
    daq_baudrate: int = Field(default=3_000_000, ge=9600, le=50_000_000)
    crank_radius_m: float = Field(default=0.01, gt=0, le=1.0,
                                  description="radius the crank is set to by hand (real rig)")


StandardKind = Literal["displacement_sensor", "masses", "daq", "conditioner"]


class StandardConfig(_Model):
    """A reference standard the station's measurements trace to (seeds the register)."""

    id: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.\-]+$")
    kind: StandardKind
    description: str = Field(default="", max_length=256)
    certificate_id: str = Field(min_length=1, max_length=128)
    issuer: str = Field(min_length=1, max_length=256)
    due_date: dt.date = Field(description="calibration due date (ISO, e.g. 2027-06-30)")
    uncertainty: float = Field(ge=0, le=1e6, description="the standard uncertainty it contributes, in "
                               "uncertainty_unit")
    uncertainty_unit: str = Field(min_length=1, max_length=32, description="e.g. m, kg, V/V, relative")


class BatchSection(_Model):
    """The nightly batch (``station batch``): the check transducer's short calibration it asks the
    station daemon for before it re-identifies (docs/batch.md)."""

    check_steps: list[StepSpec] = Field(
        default_factory=list, max_length=10, description="the check run's steps (a short plan: 2-3 steps "
        "where S, k_f and b_f are determined); empty: three of the plan's steps (first, middle, last)")
    check_top_mass_kg: float | None = Field(default=None, gt=0, le=MAX_TOP_MASS_KG,
                                            description="the check run's top mass; default rig.top_mass_kg")
    check_timeout_s: float = Field(default=1800.0, gt=0, le=86_400.0, description="how long the batch waits "
                                   "for the check run to be acquired and identified before it reports it unfinished")
    station_url: str | None = Field(default=None, pattern=r"^https?://[^\s]+$", max_length=256,
                                    description="the station daemon's address (default: http://service.host:"
                                    "service.port); its token is STATION_TOKEN or service.token")


class LabSection(_Model):
    """Users, reference standards, the register's seed."""

    overdue_standards: Literal["refuse", "warn"] = Field(
        default="refuse", description="a run with a reference standard past its due date is refused, or "
        "started with a warning in its record")
    session_minutes: float = Field(default=480.0, ge=1, le=7 * 24 * 60, description="a page login expires "
                                   "after this")
    standards: list[StandardConfig] = Field(default_factory=list, max_length=64,
                                            description="reference standards entered into the register at "
                                            "start-up when not there yet")
    signing_key: str = Field(default="signing-key.pem", min_length=1, max_length=4096,
                             description="the lab's Ed25519 private key that signs each issued certificate "
                             "(PEM, mode 0600; relative to the database's folder; station keys init)")


class ServiceSection(_Model):
    """The daemon (``station serve``): where it listens, its API token, its database, its workers.

    The token may also come from the environment variable STATION_TOKEN (which wins)."""

    host: str = Field(default="127.0.0.1", min_length=1, description="listen address (loopback by default)")
    port: int = Field(default=8080, ge=0, le=65535, description="TCP port (0: any free port)")
    stop_port: int | None = Field(default=None, ge=0, le=65535,
                                  description="TCP port of the stop port (POST /stop on a listener of its own, "
                                  "same host); unset: port + 1 (none when port is 0); 0: none")
    token: str | None = Field(default=None, min_length=8, max_length=256, pattern=r"^[\x21-\x7e]+$", repr=False,
                              description="bearer token for the endpoints that move the rig or change state")
    database: str = Field(default="station.db", min_length=1,
                          description="SQLite file of runs and jobs; relative paths are in recordings_dir")
    workers: int = Field(default=1, ge=0, le=16, description="identification worker processes "
                         "(0: jobs wait in the queue until a daemon with workers runs)")
    max_body_bytes: int = Field(default=1_048_576, ge=1024, le=64 * 2**20,
                                description="largest request body accepted, bytes (larger: 413, unread)")
    max_connections: int = Field(default=1000, ge=16, le=100_000,
                                 description="open HTTP connections at most (kept below the open-files "
                                 "limit); beyond it the oldest idle ones are closed for new clients")
    render_at_start: bool = Field(default=True, description="start the render worker (plots, report) with the "
                                  "daemon, so that the first results page does not wait for a process start; "
                                  "false: on first use")
    header_timeout_s: float = Field(default=10.0, ge=1.0, le=300.0,
                                    description="a connection that sends no complete request head within this "
                                    "after opening or after its last response is closed, s")
    rig_priority: Literal["realtime", "raised", "normal"] = Field(
        default="realtime", description="scheduling priority the rig thread and the stop port ask for (what the "
        "system gives is logged): realtime (SCHED_FIFO, else raised), raised (nice -10), normal")
    host_names: list[Annotated[str, Field(min_length=1, max_length=253, pattern=r"^[A-Za-z0-9.-]+$")]] = Field(
        default_factory=list, max_length=32,
        description="names this station is reached by besides loopback names and IP addresses (the stop port "
        "refuses a Host header naming anything else: DNS rebinding)")


class EnvironmentConfig(_Model):
    """Environmental conditions entered with the run (the certificate states them): air temperature
    in degC and relative humidity in %, with their standard uncertainties."""

    temperature_c: float | None = Field(default=None, ge=-40, le=80)
    temperature_std_c: float = Field(default=0.5, ge=0, le=20)
    relative_humidity_pct: float | None = Field(default=None, ge=0, le=100)
    relative_humidity_std_pct: float = Field(default=3.0, ge=0, le=50)

    @classmethod
    def accepted_range(cls, name: str) -> tuple[float, float]:
        """(min, max) a field accepts, inclusive, in its unit (the bounds declared above)."""
        meta = cls.model_fields[name].metadata
        lo = next(float(m.ge) for m in meta if getattr(m, "ge", None) is not None)
        hi = next(float(m.le) for m in meta if getattr(m, "le", None) is not None)
        return lo, hi


class ReferenceStandard(_Model):
    """A reference standard the calibration uses (displacement sensor, masses, DAQ/conditioner):
    its identification, calibration certificate and when that is due again (ISO date)."""

    name: str = Field(min_length=1, max_length=200)
    kind: Literal["displacement_sensor", "masses", "daq", "conditioner", "thermometer", "other"]
    id: str = Field(min_length=1, max_length=100)
    certificate_id: str = Field(min_length=1, max_length=100)
    due_date: str = Field(pattern=r"^\d{4}-\d{2}-\d{2}$")
    traceability: str = Field(default="", max_length=300)


class Party(_Model):
    """A laboratory or a customer: name, postal address (lines), e-mail and country (ISO 3166-1)."""

    name: str = Field(min_length=1, max_length=200)
    address: list[str] = Field(default_factory=list, max_length=8)
    accreditation: str = Field(default="", max_length=200)
    email: str = Field(default="", max_length=254, pattern=r"^$|^[^@\s]+@[^@\s]+\.[^@\s]+$")
    country: str = Field(default="", pattern=r"^$|^[A-Z]{2}$", description="ISO 3166-1 alpha-2 code (the "
                         "laboratory's is the DCC's country)")


class CertificateUser(_Model):
    """A named person and the role that decides what they may do with certificates."""

    name: str = Field(min_length=1, max_length=100)
    role: Literal["technician", "approver", "admin"]


class CertificateConfig(_Model):
    """What a calibration certificate names beside the run (docs/certificate.md): the laboratory, the
    customer, the place, the reference standards; number_prefix of the certificate numbers;
    dcc_schema: a path to the DCC XML Schema every DCC is validated against before issue."""

    laboratory: Party = Party(name="sinecal calibration laboratory")
    customer: Party | None = None
    place: str = Field(default="", max_length=200)
    standards: list[ReferenceStandard] = Field(default_factory=list, max_length=50)
    number_prefix: str = Field(default="SC", pattern=r"^[A-Za-z0-9\-]{1,16}$")
    dcc_schema: str | None = Field(default=None, max_length=4096)
    users: list[CertificateUser] = Field(default_factory=list, max_length=200)


ModelChoice = Literal["auto", "sdof", "coupled", "h1", "h2"]  # "auto": fd picks Eq. 9 or Eq. 8 from the data
MAX_METHODS = 6


class MethodChoice(_Model):
    """One identification a finished run gets: an estimator (``station.ident.names.METHODS``), the
    model it fits (``auto``: Eq. 9, or Eq. 8 when the data demand and determine it; ``h2``/``h1``:
    the paper's digital Eq. 11/10) and the seed of its random draws (the swarm's)."""

    method: Method
    model: ModelChoice | None = Field(default=None, description="default: the method's first model "
                                      "(fd: auto, oe: sdof, pso/pso+/rls: h2)")
    seed: int = Field(default=0, ge=0, le=2**31 - 1, description="seed of the method's random draws")

    @model_validator(mode="after")
    def _model_of_method(self) -> MethodChoice:
        allowed = MODELS_OF_METHOD[self.method]
        if self.model is not None and self.model not in allowed:
            raise ValueError(f"method {self.method!r} is defined for the models {', '.join(allowed)}, "
                             f"not {self.model!r}")
        return self

    @property
    def model_key(self) -> str:
        return self.model or MODELS_OF_METHOD[self.method][0]

    @property
    def label(self) -> str:
        return f"{self.method}/{self.model_key}"


def _default_methods() -> list[MethodChoice]:
    return [MethodChoice(method=Method.FD, model="auto"), MethodChoice(method=Method.PSO_PLUS, model="h2")]


def check_method_list(methods: list[MethodChoice]) -> list[MethodChoice]:
    """An ordered list of identifications, the first being the primary: no method twice with the
    same model (one result each), and fd's ``auto`` not beside an explicit fd model."""
    seen: dict[tuple[str, str], int] = {}
    for i, m in enumerate(methods):
        key = (m.method, m.model_key)
        if key in seen:
            raise ValueError(f"{m.label} is listed twice (entries {seen[key]} and {i}); each (method, model) "
                             "gives one result")
        seen[key] = i
    fd_models = {k[1] for k in seen if k[0] == "fd"}
    if "auto" in fd_models and len(fd_models) > 1:
        raise ValueError("fd/auto already gives fd/sdof or fd/coupled: list either auto or explicit fd models")
    return methods


class SwarmConfig(_Model):
    """The paper's swarm (PSO/PSO+) size; null keeps Section 5.1's (200 particles, 1000 iterations
    for Eq. 11, 2000 for Eq. 10).  Smaller swarms are for quick checks, not calibrations."""

    n_particles: int | None = Field(default=None, ge=2, le=5000)
    n_iterations: int | None = Field(default=None, ge=1, le=20000)


class IdentificationConfig(_Model):
    """Identification: which estimators every finished run gets (``methods``, the first being the
    primary result) and the measurement chain's own uncertainty (``station.ident.inputs``)."""

    methods: list[MethodChoice] = Field(default_factory=_default_methods, min_length=1, max_length=MAX_METHODS,
                                        description="ordered (method, model) list; the first is the primary "
                                        "result, the others are computed after it, beside it")
    swarm: SwarmConfig = SwarmConfig()
    chain: MeasurementChain = MeasurementChain()

    @model_validator(mode="after")
    def _methods(self) -> IdentificationConfig:
        check_method_list(self.methods)
        return self


class StationConfig(_Model):
    """A whole station configuration file."""

    station: StationSection = StationSection()
    transducer: TransducerConfig
    rig: RigConfig
    conditioner: ConditionerConfig = ConditionerConfig()
    displacement_sensor: DisplacementSensorConfig = DisplacementSensorConfig()
    daq: DaqConfig = DaqConfig()
    plan: PlanConfig
    identification: IdentificationConfig = IdentificationConfig()
    environment: EnvironmentConfig = EnvironmentConfig()
    certificate: CertificateConfig = CertificateConfig()
    devices: DevicesConfig = DevicesConfig()
    simulation: SimulationConfig | None = None
    service: ServiceSection = ServiceSection()
    lab: LabSection = LabSection()
    batch: BatchSection = BatchSection()

    @model_validator(mode="after")
    def _drive_profile(self) -> StationConfig:
        """rig.motor.profile must load (drivers.motor.profile); the run checks its steps against the
        drive's frequency range before anything moves (the ranges here also serve the simulator)."""
        # here: the drive's driver (its Modbus client) loads with the first configuration checked, not
        # with every process that reads a configuration's types (an identification worker)
        from drivers.motor.errors import RegisterMapError
        from drivers.motor.profile import load_profile

        try:
            load_profile(self.rig.motor.profile)
        except RegisterMapError as exc:
            raise ValueError(f"rig.motor.profile: {exc}") from None
        return self

    @model_validator(mode="after")
    def _daq_link_budget(self) -> StationConfig:
        """devices.daq_baudrate must carry daq.sample_rate_hz x 2 channels even if SLIP escaped every
        byte (drivers.daq.protocol.link_budget; docs/daq-protocol.md, link budget)."""
        if self.devices.daq_link != "uart":
            return self  # a USB-CDC link ignores the baud rate: checked at connect (drivers.daq.bridge)
        budget = link_budget(self.daq.sample_rate_hz, self.devices.daq_baudrate)
        if not budget.ok:
            raise ValueError(f"devices.daq_baudrate / daq.sample_rate_hz: {budget.message()}")
        return self


def _field_bounds(loc: tuple[Any, ...]) -> list[str]:
    """The declared bounds of the field at ``loc`` in StationConfig, e.g. ['> 0', '<= 1.0'] (fields of
    pydantic models, and of the drivers' dataclasses such as the effect catalogue)."""
    model: Any = StationConfig
    metadata: list[Any] = []
    for part in loc:
        if isinstance(part, int):  # list index: stay on the item model
            continue
        if isinstance(model, type) and issubclass(model, BaseModel) and part in model.model_fields:
            info = model.model_fields[part]
            ann, metadata = info.annotation, list(info.metadata)
        elif dataclasses.is_dataclass(model) and part in {f.name for f in dataclasses.fields(model)}:
            ann = get_type_hints(model, include_extras=True)[part]
            metadata = list(getattr(ann, "__metadata__", ()))
            ann = getattr(ann, "__origin__", ann) if metadata else ann
        else:
            return []
        args = [a for a in getattr(ann, "__args__", (ann,)) if isinstance(a, type)]
        model = next((a for a in args if issubclass(a, BaseModel) or dataclasses.is_dataclass(a)), ann)
    out = []
    for meta in metadata:
        for key, sym in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<")):
            if getattr(meta, key, None) is not None:
                out.append(f"{sym} {getattr(meta, key)}")
    return out


SECRET_KEYS = frozenset({"token"})  # their values are never quoted in an error message
SECRET_SECTIONS = frozenset({"service"})  # the section holding the token: a misspelt key's value is not quoted


def _describe_error(err: ErrorDetails) -> str:
    loc = ".".join(str(p) for p in err["loc"]) or "(top level)"
    bounds = _field_bounds(tuple(err["loc"]))
    if err["type"] in ("extra_forbidden", "unexpected_keyword_argument"):
        if err["loc"] and str(err["loc"][0]) in SECRET_SECTIONS:
            return f"{loc}: unknown key"  # its value is not quoted: it may be the token under a misspelt key
        return f"{loc}: unknown key (received {quote(err['input'])})"
    if err["type"] in ("missing", "missing_argument"):
        return f"{loc}: required key is missing"
    if not err["loc"] and err["type"] == "value_error":  # a check across sections: the message says it all
        return str(err["msg"]).removeprefix("Value error, ")
    allowed = f"; allowed: value {' and '.join(bounds)}" if bounds else ""
    if SECRET_KEYS & {str(p) for p in err["loc"]}:
        value = err.get("input")
        shown = f"<not shown, {len(value)} characters>" if isinstance(value, str) else "<not shown>"
        msg = "expected at least 8 printable ASCII characters without spaces" if err["type"] in (
            "string_pattern_mismatch", "string_too_short") else err["msg"]
        return f"{loc} = {shown}: {msg}"
    return f"{loc} = {quote(err.get('input'))}: {err['msg']}{allowed}"


def parse_config(data: Any, source: str = "<config>") -> StationConfig:
    """Validate a parsed YAML mapping; raises ConfigError listing every problem."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level, got {type(data).__name__}")
    try:
        return StationConfig.model_validate(data)
    except ValidationError as exc:
        lines = "\n  ".join(_describe_error(e) for e in exc.errors())
        raise ConfigError(f"{source}: invalid configuration:\n  {lines}") from None


def load_config(path: str | Path) -> StationConfig:
    """Read and validate a station YAML file."""
    p = Path(path)
    text = read_text_limited(p, MAX_YAML_BYTES, "configuration", ConfigError, say_what=True)
    return parse_config(load_yaml(text, str(p), ConfigError), str(p))


def config_to_yaml(cfg: StationConfig) -> str:
    """The configuration as YAML (the snapshot stored in every recording; never the API token)."""
    return yaml.dump(cfg.model_dump(mode="json", exclude_none=True, exclude={"service": {"token"}}),
                     Dumper=getattr(yaml, "CSafeDumper", yaml.SafeDumper), sort_keys=False)  # libyaml's: 3x faster


def default_config_path() -> Path:
    """The shipped ``config/sim-5kN.yaml`` (the station's default)."""
    return config_file("sim-5kN.yaml")


def to_rig_physics(cfg: StationConfig) -> rp.RigPhysics:
    """The simulator's physics from a configuration with a ``simulation`` section."""
    sim = cfg.simulation
    if sim is None:
        raise ConfigError("the configuration has no 'simulation' section; the simulated rig needs one")
    t = cfg.transducer
    m_e = sim.truth.end_mass_kg or t.end_mass_kg
    if m_e is None:
        raise ConfigError("simulation needs an end mass: set simulation.truth.end_mass_kg "
                          "or transducer.end_mass_kg")
    return rp.RigPhysics(
        transducer=rp.Transducer(
            k_f=sim.truth.k_f, b_f=sim.truth.b_f, m_e=m_e, m_l=sim.truth.load_mass_kg or cfg.rig.load_mass_kg,
            sensitivity_V_per_N=sim.truth.sensitivity_V_per_N or t.sensitivity_V_per_N,
            capacity_N=t.capacity_N),
        displacement_sensor=rp.DisplacementSensor(
            gain_V_per_m=sim.truth.displacement_gain_V_per_m or cfg.displacement_sensor.gain_V_per_m,
            noise_m=sim.displacement_noise_m),
        conditioner=rp.Conditioner(gain=cfg.conditioner.gain, offset_V=cfg.conditioner.offset_V,
                                   noise_V=sim.conditioner_noise_V),
        adc=rp.Adc(bits=cfg.daq.adc_bits, displacement_range_V=cfg.daq.displacement_range_V,
                   force_range_V=cfg.daq.force_range_V),
        effects=sim.effects,
        sample_rate_hz=cfg.daq.sample_rate_hz,
    )
