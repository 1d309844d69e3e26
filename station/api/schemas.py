"""Request and response schemas of the HTTP API (the OpenAPI document is generated from these).

The request body of ``POST /runs`` is ``station.run.request.RunRequest`` itself (one definition
for the daemon, the CLI and the nightly batch); everything else here is a response.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, Literal, overload

from pydantic import BaseModel, ConfigDict, Field

from station.lab.store import RunState
from station.run.procedure import StepState
from station.service.results import StepResponse
from station.vocabulary import Flag, Method, Model, Severity

# closed sets of values: enumerations in the OpenAPI document (checked against their sources in the tests)
MethodName = Method  # the domain's closed sets (station.ident.names), not re-declared here
ModelName = Model
EStopSource = Literal["page", "api", "controller", "drive", "link"]  # link: the rig process lost the web process
ModelChoiceName = Literal["auto", "sdof", "coupled", "h1", "h2"]  # station.config.ModelChoice
MethodStatus = Literal["pending", "running", "done", "refused", "failed"]  # station.run.methods.STATUSES


class OutModel(BaseModel):
    """Base of the response schemas: no field beyond those declared."""

    model_config = ConfigDict(extra="forbid")


@overload
def utc(ts: float) -> datetime: ...
@overload
def utc(ts: float | None) -> datetime | None: ...
def utc(ts: float | None) -> datetime | None:
    """UNIX seconds as an aware UTC datetime (None stays None)."""
    return None if ts is None else datetime.fromtimestamp(ts, UTC)


class Problem(OutModel):
    """A refusal as RFC 9457 problem details (``application/problem+json``; station/api/problems.py)."""

    type: str = Field(description="the kind of refusal, machine-readable: urn:sinecal:problem:<kind> "
                      "(e.g. not-logged-in, run-not-found, rig-busy, invalid-input)")
    title: str = Field(description="the kind of refusal in words")
    status: int = Field(description="the HTTP status")
    detail: str = Field(description="what went wrong this time and what to do, for the operator")
    instance: str | None = Field(default=None, description="the request's path")


ErrorOut = Problem  # the name the routes use


class FieldError(BaseModel):
    """One problem with the request (FastAPI's validation error item; may carry ``ctx``)."""

    model_config = ConfigDict(extra="allow")

    loc: list[str | int] = Field(description="where the offending value is, e.g. ['body', 'steps', 1, "
                                 "'crank_radius_m']")
    msg: str
    type: str
    input: Any = None


class ValidationProblem(Problem):
    """Invalid input (422): the problem, with each offending field in ``errors``."""

    errors: list[FieldError] = Field(description="each offending value: where (`loc`) and why (`msg`)")


ValidationErrorOut = ValidationProblem  # the name the routes use


class RunLinks(OutModel):
    self: str
    events: str
    results: str
    recording: str
    abort: str


class PlannedStepOut(OutModel):
    index: int
    crank_frequency_hz: float = Field(description="Hz")
    crank_radius_m: float = Field(description="m")
    settle_s: float = Field(description="s")
    record_s: float = Field(description="s")


class MethodStateOut(OutModel):
    """How one of the run's listed identifications (``identification.methods``) went."""

    method: MethodName
    model: ModelChoiceName = Field(description="as listed (fd's `auto`: the model comes with the result)")
    primary: bool = Field(description="the first listed: the run's result")
    status: MethodStatus = Field(description="pending, running, done, or refused / failed (see `reason`); a "
                                 "secondary method's refusal or failure never fails the run")
    seed: int = Field(description="seed of the method's random draws (the swarm's)")
    result_name: str | None = Field(description="the stored result (done only)")
    result_model: ModelName | None = Field(description="the model the result is for")
    compute_s: float | None = Field(description="wall-clock time of the identification in its worker, s")
    cpu_s: float | None = Field(description="processor time of the identification, s")
    reason: str = Field(description="why there is no result (refused, failed)")


class RunStatus(OutModel):
    """A run's state and live progress."""

    id: str
    state: RunState
    transducer_id: str
    top_mass_kg: float
    created: datetime
    started: datetime | None
    ended: datetime | None
    current_step: int | None = Field(description="index of the step on the rig (0-based), None before the first")
    n_steps: int
    step_state: StepState = Field(description="where the step on the rig is; stopping: every step is recorded "
                                  "and the crank ramps down to standstill; aborted, failed or interrupted: "
                                  "the run ended there")
    progress: float = Field(ge=0, le=1, description="fraction of the acquisition done")
    samples: int = Field(description="samples acquired so far")
    lost_samples: int = Field(description="samples the DAQ link lost in this run (0 expected)")
    message: str
    reason: str = Field(description="why the run ended as it did (empty when completed)")
    recording: str | None = Field(description="file name of the HDF5 recording in the recordings folder")
    steps: list[PlannedStepOut]
    links: RunLinks
    methods: list[MethodStateOut] = Field(default=[], description="the listed identifications of a run this "
                                          "daemon identified since it started, as they go (the stored ones: "
                                          "GET /runs/{id}/results)")
    operator: str = Field(default="", description="the user who started the run ('' before users existed)")
    standards: list[str] = Field(default_factory=list, description="ids of the reference standards the run used")


class RunList(OutModel):
    count: int
    runs: list[RunStatus]


class RunAccepted(OutModel):
    id: str
    state: RunState
    links: RunLinks


class EstimateOut(OutModel):
    """One identified quantity with its uncertainty (a single recording's or a campaign's)."""

    value: float | None = Field(description="estimate in `unit`; None when not identifiable or refused")
    std: float | None = Field(description="combined standard uncertainty in `unit` (the budget's)")
    unit: str
    identifiable: bool
    reason: str = ""
    flag: Flag = Field(default=Flag.NONE, description="poorly_determined, or conditional (on an assumption)")


class ParameterOut(EstimateOut):
    name: str


class CovarianceOut(OutModel):
    """Covariance of estimated parameters (names and units in matrix order); its diagonal is the
    square of their stated standard uncertainties."""

    names: list[str]
    units: list[str]
    matrix: list[list[float | None]] = Field(description="covariance in the parameters' units (products)")


class CheckOut(OutModel):
    """A finding of the identification's input checks."""

    name: str
    severity: Severity
    step: int | None
    message: str
    values: dict[str, Any] = Field(description="the numbers behind it; `recording`: the file a recording's own "
                                   "check concerns (campaigns)")


class FitOut(OutModel):
    mse: float | None = Field(description="mean square force residual, V^2")
    residual_rms_V: list[float | None]
    chi2_per_dof: float | None
    n_points: int


class IdentifiabilityOut(OutModel):
    names: list[str]
    condition_number: float | None
    correlations: list[list[float | None]]
    identifiable: list[bool]
    reasons: list[str]


class BudgetOut(OutModel):
    """A parameter's uncertainty budget: each source's standard uncertainty and their combination."""

    contributions: dict[str, float | None] = Field(description="standard uncertainty per source, in `unit`")
    combined: float
    unit: str
    dof: dict[str, float] | None = Field(None, description="finite degrees of freedom per source (the others "
                                         "infinite): the noise term's when it was scaled by chi^2/dof")


class MassAssumptionOut(OutModel):
    value: float | None = Field(description="kg")
    std: float | None = Field(description="kg")
    source: str = Field(description="where the value comes from (config, request, campaign, ...)")


class RunMassOut(OutModel):
    run_id: str
    value: float | None = Field(description="kg")
    std: float | None = Field(description="kg")


class MeasurementChainOut(BaseModel):
    """The measurement chain's stated uncertainties (relative, deg, s, Hz; further keys allowed)."""

    model_config = ConfigDict(extra="allow")

    gain_rel_std: float | None = None
    flatness_rel_std: float | None = None
    phase_offset_std_deg: float | None = None
    phase_std_deg: float | None = None
    delay_std_s: float | None = None


class AssumptionsOut(BaseModel):
    """What a result rests on, stated with it: masses, the measurement chain, the model's structure."""

    model_config = ConfigDict(extra="allow")

    end_mass_kg: MassAssumptionOut | None = None
    load_mass_kg: MassAssumptionOut | None = None
    measurement_chain: MeasurementChainOut | None = None
    displacement_chain: dict[str, Any] | None = None
    structure: dict[str, Any] | None = Field(default=None, description="the model structure (equation, coupling, "
                                             "displacement chain) and what the data determine of it")


class DeterminedOut(BaseModel):
    """A quantity the data determine whatever the assumptions: value, combined standard uncertainty,
    unit (further keys: the budget's sources, a range, a note)."""

    model_config = ConfigDict(extra="allow")

    value: float | None
    combined: float | None = None
    unit: str


class SkippedStepOut(OutModel):
    """A step left out of H(f), and why."""

    step: int
    reason: str


class AgreementOut(OutModel):
    """A parameter of a method against the primary's: difference and its combined standard uncertainty."""

    difference: float | None = Field(description="this method's value minus the primary's, in `unit`")
    combined_std: float | None = Field(description="sqrt(u^2 + u_primary^2), in `unit`")
    z: float | None = Field(description="difference / combined_std (|z| > 2: they disagree)")
    unit: str
    reason: str = Field(description="why there is no z (a method withholds the parameter, and why)")


class MethodResultOut(MethodStateOut):
    """A listed identification with its stored result (parameters, fit, checks, budget) and its
    agreement with the primary result."""

    parameters: list[ParameterOut] = []
    fit: FitOut | None = None
    identifiability: IdentifiabilityOut | None = None
    notes: list[str] = []
    checks: list[CheckOut] = []
    budget: dict[str, BudgetOut] = Field(default={}, description="per parameter")
    agreement: dict[str, AgreementOut] = Field(default={}, description="per parameter, against the primary "
                                               "result (empty for the primary and for a method without result)")


class EnvironmentOut(OutModel):
    """The conditions the run's recording stored (its start document): air temperature in degC,
    relative humidity in %, their standard uncertainties, and where they came from."""

    temperature_c: float | None
    temperature_std_c: float | None
    relative_humidity_pct: float | None
    relative_humidity_std_pct: float | None
    source: str = Field(description="'entered with the run' or 'simulated room sensor'")


class RunResults(OutModel):
    id: str
    state: RunState
    recording: str
    method: MethodName | None
    model: ModelName | None
    parameters: list[ParameterOut]
    fit: FitOut | None
    identifiability: IdentifiabilityOut | None
    notes: list[str]
    checks: list[CheckOut] = []
    budget: dict[str, BudgetOut] = Field(default={}, description="per parameter")
    assumptions: AssumptionsOut = Field(default_factory=lambda: AssumptionsOut(),
                                        description="end and load mass, measurement chain, displacement chain, "
                                        "and the model structure (Eq. 9 or Eq. 8, the coupling this plan cannot "
                                        "exclude)")
    determined: dict[str, DeterminedOut] = Field(default={}, description="what the data determine whatever the "
                                                 "end mass (S M, natural frequency, damping ratio) and the coupling "
                                                 "(series stiffness; the range of k_f alone conditional on a stiff "
                                                 "coupling)")
    covariance: CovarianceOut | None = Field(default=None, description="of the parameters that have a value, as "
                                             "the identification stored it (null for results stored before it was)")
    frequency_response: list[StepResponse]
    skipped_steps: list[SkippedStepOut]
    units: dict[str, str]
    plots: dict[str, str] = Field(description="plot name -> URL of its PNG")
    report: str = Field(description="URL of the calibration report (HTML)")
    discrepancy: str = Field(description="URL of the model-gap analysis")
    lost_samples: int
    environment: EnvironmentOut | None = Field(default=None, description="the conditions the recording stored "
                                               "(null: none were entered or measured)")
    methods: list[MethodResultOut] = Field(default=[], description="every listed identification side by side, "
                                           "the primary first (the top-level fields are the primary's); empty for "
                                           "runs identified before methods were listed")


class DiscrepancyOut(BaseModel):
    """The model-gap analysis (``DiscrepancyResult.to_json``): gaps in V, effects added."""

    model_config = ConfigDict(extra="allow")

    base_gap: float | None = None
    final_gap: float | None = None
    effects: list[dict[str, Any]] = []
    parameters_before: dict[str, Any] = {}
    parameters_after: dict[str, Any] = {}
    unexplained: list[str] = []
    ties: list[dict[str, Any]] = Field(default=[], description="models the data do not decide between")
    notes: list[str] = []


class DriveOut(OutModel):
    """The drive read back after a stop (the station's own stops and the emergency stop)."""

    after: str = Field(description="which stop, e.g. 'the emergency stop'")
    standstill: bool | None = Field(description="the drive reports standstill (false: still turning after the "
                                    "time a healthy drive needs; null: it could not be read)")
    speed_hz: float | None = Field(description="crank frequency the drive reported last, Hz")
    fault_code: int | None
    fault_name: str | None
    waited_s: float = Field(description="how long the station read it back, s")
    at: str = Field(description="when (ISO 8601, UTC)")
    error: str | None
    detail: str


class StopOut(OutModel):
    accepted: bool = True
    motor_stopped: bool = Field(description="the drive, read back after the command, reports standstill "
                                "(false: still turning, not readable, or the command was not taken)")
    stop_commanded: bool = Field(default=False, description="the motor controller took the emergency stop")
    drive: DriveOut | None = Field(default=None, description="what the drive reported (null: no link)")
    aborted_runs: list[str]
    detail: str


class AcknowledgeIn(BaseModel):
    """Who acknowledges the emergency stop (recorded with the time), and an optional note."""

    model_config = ConfigDict(extra="forbid", strict=True)

    operator: str = Field(default="", max_length=64, description="the operator at the rig, if not the user "
                          "who acknowledges (who acknowledges is the logged-in user or the token's)")
    note: str = Field(default="", max_length=500, description="e.g. what was checked before the restart")


class AcknowledgeOut(OutModel):
    acknowledged: list[int] = Field(description="ids of the emergency stops acknowledged (empty: none latched)")
    by: str
    at: datetime
    detail: str = Field(description="what the motor controller reports after its fault reset")
    latched: bool


class EStopState(OutModel):
    latched: bool | None = Field(description="an emergency stop waits for an operator's acknowledgement "
                                 "(held in memory: known even when the database cannot be read)")
    since: str | None = None
    source: EStopSource | None = Field(default=None, description="page, api, controller or drive (the drive did "
                                       "not come to rest after a stop)")
    detail: str | None = None
    count: int = 0
    last_acknowledged: str | None = None
    last_acknowledged_by: str | None = None


class AbortOut(OutModel):
    id: str
    state: RunState
    detail: str


class MotorLink(OutModel):
    connected: bool
    watchdog_error: str | None
    link_error: str | None = Field(default=None, description="why the motor controller cannot be reached "
                                   "(None: reachable, or the failure is the DAQ's)")


class DaqLink(OutModel):
    link_error: str | None


class RigHealth(OutModel):
    connected: bool
    error: str | None
    description: str
    motor: MotorLink
    daq: DaqLink
    simulated: bool


class DatabaseHealth(OutModel):
    ok: bool = Field(description="the database answers and takes writes")
    journal_mode: str | None
    pending_writes: int = Field(default=0, description="changes waiting for the database (retried until taken)")
    error: str | None = Field(default=None, description="why the database does not answer or take writes")


class WorkerHealth(OutModel):
    processes: int
    started: bool
    crashes: int
    jobs: dict[str, int]
    unrecorded: dict[str, str] = Field(
        default_factory=dict, description="run id -> an identification outcome the database has not taken yet "
        "(e.g. its disk is full) and why; written again every few seconds, and `status` is `degraded` meanwhile")


class DiskHealth(OutModel):
    ok: bool
    free_bytes: int = Field(description="free space on the recordings disk, bytes")
    reserve_bytes: int = Field(description="kept free (station.min_free_mb), bytes")
    reserve_file: bool = Field(description="the reserve file that lets a recording close on a full disk is in place")
    reserve_used: int = Field(description="times a full disk used the reserve file since the start")
    detail: str | None


class UnreadableRecordingOut(OutModel):
    file: str = Field(description="file name in the recordings folder")
    error: str


class RecordingsCheckOut(OutModel):
    """The start-up check of the recordings folder (recordings damaged by an interrupted in-place
    write of an older station: repaired, or named when they cannot be read)."""

    repaired: list[str] = Field(description="recordings whose write flag was cleared (content copied and verified)")
    unreadable: list[UnreadableRecordingOut] = Field(description="recordings that cannot be read; left as they are")
    temporaries_removed: list[str] = Field(description="temporary files of interrupted writes, removed")
    notes: list[str]


class AuditChainHealth(OutModel):
    ok: bool
    detail: str


class HealthOut(OutModel):
    status: Literal["ok", "degraded"]
    estop: EStopState
    disk: DiskHealth
    drive: DriveOut | None = Field(default=None, description="the drive read back after the last stop")
    rig: RigHealth
    database: DatabaseHealth
    worker: WorkerHealth
    active_run: str | None
    uptime_s: float
    recordings: RecordingsCheckOut
    audit_chain: AuditChainHealth | None = Field(default=None, description="the audit trail's hash chain as last "
                                                 "walked (start-up, /integrity, before an issue); broken: degraded")


class RangeOut(OutModel):
    min: float
    max: float


class DriveLimitsOut(OutModel):
    """What the configured drive profile declares (its set-point and ramp registers' ranges)."""

    profile: str
    crank_frequency_hz: RangeOut = Field(description="the set point's range, Hz")
    acceleration_hz_per_s: RangeOut = Field(description="the ramp rates its ramp register(s) take, Hz/s")


class LimitsOut(OutModel):
    crank_frequency_hz: RangeOut
    crank_radius_m: RangeOut
    peak_force_limit_N: float = Field(description="peak |F| = M (g + r w^2) must stay below this")
    moving_mass_without_top_kg: float = Field(description="adaption mass + end mass; M = this + top mass")
    top_mass_kg: RangeOut
    steps: RangeOut
    acceleration_hz_per_s: float
    drive: DriveLimitsOut = Field(description="the drive's own limits; a plan beyond them is refused (422)")


class EnvironmentFormOut(OutModel):
    """What a run request's ``environment`` accepts and what a run states when it is left out."""

    temperature_c: RangeOut = Field(description="accepted air temperature, degC")
    relative_humidity_pct: RangeOut = Field(description="accepted relative humidity, %")
    default_temperature_c: float | None = Field(description="the configuration's environment (null: none)")
    default_relative_humidity_pct: float | None = Field(description="the configuration's environment (null: none)")
    otherwise: str = Field(description="what a run states without entered or configured values: "
                           "'simulated room sensor' or 'not recorded'")


class StationOut(OutModel):
    name: str
    transducer_id: str
    capacity_N: float
    default_top_mass_kg: float
    simulated: bool
    limits: LimitsOut
    default_settle_s: float
    default_record_s: float
    default_steps: list[dict[str, float]]
    token_required: list[str] = Field(description="endpoints that need the bearer token")
    stop_port: int | None = Field(default=None, description="the stop port: POST /stop on a listener of its own "
                                  "(same host; null: none)")
    environment: EnvironmentFormOut | None = Field(default=None, description="the run request's room conditions")


class CertificateIssueIn(BaseModel):
    """Issue a run's certificate: the approver is the authenticated user (an approver who did not
    run it); prepared_by defaults to the run's operator; a correction names the certificate it
    replaces and why."""

    model_config = ConfigDict(extra="forbid")
    prepared_by: str | None = Field(None, min_length=1, max_length=100, description="default: the run's operator")
    note: str = Field("", max_length=500, description="the approval's note (audit trail)")
    replaces: str | None = Field(None, pattern=r"^[A-Za-z0-9\-]{1,40}$")
    reason: str = Field("", max_length=500)


class SigningKeyOut(OutModel):
    """The lab's public signing key."""

    algorithm: str = Field(description="Ed25519")
    fingerprint: str = Field(description="SHA-256 of the raw public key, as printed on the certificates")
    public_key: str = Field(description="PEM (SubjectPublicKeyInfo)")


class CertificateWithdrawIn(BaseModel):
    """Withdraw an issued certificate: why (kept in the audit trail)."""

    model_config = ConfigDict(extra="forbid")
    reason: str = Field(min_length=10, max_length=500)


class CertificateOut(OutModel):
    """An issued certificate in the register."""

    number: str
    transducer_id: str
    run_id: str
    recording: str
    issued_at: str = Field(description="ISO 8601, UTC")
    approved_by: str
    replaces: str | None
    replaced_by: str | None = Field(description="the certificate that replaces (withdraws) this one")
    prepared_by: str = Field(default="", description="the lab user who prepared it")
    withdrawn: str | None = Field(default=None, description="why it is no longer in force (replaced or withdrawn)")
    html: str
    pdf: str
    xml: str


class CertificateList(OutModel):
    certificates: list[CertificateOut]
