"""Request and response schemas of the lab's endpoints: the register, users and sessions, the audit
trail, approvals and a transducer's history."""

from __future__ import annotations

import datetime as dt
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

from station.api.schemas import OutModel
from station.config import StandardKind
from station.lab.users import MIN_PASSWORD, NAME_PATTERN, Role

ID_PATTERN = r"^[A-Za-z0-9_.\-]{1,64}$"


class _In(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)


class TransducerIn(_In):
    """A transducer's nominal data (N, V/N, kg) and who owns it."""

    type: str = Field(default="", max_length=128, description="make and model")
    serial: str = Field(default="", max_length=128)
    capacity_N: float = Field(gt=0, le=1e7, description="N")
    sensitivity_V_per_N: float = Field(gt=0, le=1.0, description="nominal bridge output, V/N")
    end_mass_kg: float | None = Field(default=None, gt=0, le=100, description="kg")
    end_mass_std_kg: float | None = Field(default=None, ge=0, le=100, description="standard uncertainty, kg")
    owner: str = Field(default="", max_length=256, description="owner or customer")


class TransducerOut(TransducerIn):
    id: str
    updated: float = Field(description="UNIX s")
    updated_by: str


class StandardIn(_In):
    """A reference standard: its calibration certificate and the uncertainty it contributes."""

    kind: StandardKind
    description: str = Field(default="", max_length=256)
    certificate_id: str = Field(min_length=1, max_length=128)
    issuer: str = Field(min_length=1, max_length=256)
    due_date: str = Field(pattern=r"^\d{4}-\d{2}-\d{2}$", description="calibration due date (ISO, YYYY-MM-DD)")
    uncertainty: float = Field(ge=0, le=1e6, description="standard uncertainty, in uncertainty_unit")
    uncertainty_unit: str = Field(min_length=1, max_length=32)
    in_use: bool = Field(default=True, description="used by runs that name no standards")


    @field_validator("due_date")
    @classmethod
    def _a_date(cls, v: str) -> str:
        dt.date.fromisoformat(v)  # ValueError: e.g. 2027-02-30
        return v


class StandardOut(OutModel):
    id: str
    kind: str
    description: str
    certificate_id: str
    issuer: str
    due_date: str
    uncertainty: float
    uncertainty_unit: str
    in_use: bool
    overdue: bool
    updated: float
    updated_by: str


class RegisterOut(OutModel):
    mounted: str | None = Field(description="id of the transducer mounted on the station")
    transducers: list[TransducerOut]
    standards: list[StandardOut]
    overdue_policy: str = Field(description="refuse or warn (lab.overdue_standards)")


class MountIn(_In):
    transducer_id: str = Field(pattern=ID_PATTERN)


class LoginIn(_In):
    name: str = Field(min_length=1, max_length=64)
    password: str = Field(min_length=1, max_length=256)


class UserOut(OutModel):
    name: str
    role: Role
    disabled: bool
    permissions: list[str]


class UserRowOut(UserOut):
    """A user in the administrators' list, with the last change of the account (audit trail)."""

    changed: float | None = Field(default=None, description="the last change (role, password, disabled), UNIX s")
    changed_by: str | None = Field(default=None, description="who made the last change")


class RoleOut(OutModel):
    name: Role
    permissions: list[str]


class UsersPolicyOut(OutModel):
    """The rules a user's record must meet (the page shows them beside its fields)."""

    roles: list[RoleOut] = Field(description="the closed set of roles (one per user) and what each allows")
    min_password: int = Field(description="a password's least length, characters")
    name_pattern: str = Field(description="a user name's pattern (regular expression)")


class MeOut(OutModel):
    user: UserOut | None = Field(description="None: not logged in (reading on loopback is open)")
    via: str | None = Field(default=None, description="token or session")
    expires: float | None = Field(default=None, description="the session's end, UNIX s")


class UserIn(_In):
    role: Role = Field(strict=False, description="technician, approver or admin")
    password: str | None = Field(default=None, min_length=MIN_PASSWORD, max_length=256,
                                 description="a new password (at least 10 characters); unchanged if absent")
    disabled: bool = False


class UserPath(_In):
    name: str = Field(pattern=NAME_PATTERN)


class TokenIn(_In):
    label: str = Field(default="", max_length=128, description="what the token is for (a CI job, a script)")


class TokenOut(OutModel):
    user: str
    label: str
    token: str = Field(description="shown once; only its hash is stored")


class AuditEntryOut(OutModel):
    id: int
    at: float = Field(description="UNIX s")
    who: str
    action: str
    target: str
    details: dict[str, Any]
    files: dict[str, str | None] = Field(default_factory=dict, description="SHA-256 of the files the entry "
                                         "concerns (paths in the recordings folder; null: removed on purpose)")
    hash: str = Field(default="", description="the entry's link in the hash chain (docs/operations.md)")


class LockOut(OutModel):
    key: str = Field(description="user:<name> or client:<address>")
    failures: int = Field(description="failed logins in a row")
    locked_until: float = Field(description="UNIX s")


class TokenRowOut(OutModel):
    id: str = Field(description="the first 12 hex digits of the token's SHA-256 (never the token)")
    user: str
    label: str
    created: float | None = Field(description="UNIX s")
    revoked: float | None = Field(description="UNIX s, or null while it is valid")


class ChainBreakOut(OutModel):
    id: int = Field(description="the audit entry where the chain stops holding")
    reason: str
    excepted_by: int | None = Field(description="the administrator's reviewed exception (an audit entry), if any")


class IntegrityReportOut(OutModel):
    """The audit chain walked and every file it vouches for compared with the recordings folder."""

    ok: bool
    chain_ok: bool
    entries: int
    head_id: int
    head: str = Field(description="the newest entry's hash")
    breaks: list[ChainBreakOut]
    files: list[str] = Field(description="each file that is missing, differs, or is not in the trail")
    records: list[str] = Field(default_factory=list, description="each row of the lab's tables (transducer "
                               "policies, adjustments) changed, added or deleted outside the station")
    detail: str


class ExceptionIn(_In):
    entry: int = Field(ge=1, le=2**62, description="the broken link's entry id, as /integrity names it")
    reason: str = Field(min_length=10, max_length=2000, description="what was reviewed and why it is accepted")


class AuditOut(OutModel):
    count: int
    entries: list[AuditEntryOut]
    broken: list[int] = Field(default_factory=list, description="entries of this page that do not hold (content "
                              "not matching its hash, a link not matching the entry before; for deleted "
                              "entries the first missing id): the trail was changed outside the station")


class ApproveIn(_In):
    note: str = Field(default="", max_length=500)


class ApprovalOut(OutModel):
    run_id: str
    approved_by: str
    audit_id: int
    note: str
    sha256: str
    operator: str
    recording: str | None


class IntegrityOut(OutModel):
    run_id: str
    recording: str
    sha256: str
    stored: bool = Field(description="a SHA-256 was stored when the recording was closed (and matches)")


class HistoryOut(OutModel):
    transducer: TransducerOut
    runs: list[dict[str, Any]] = Field(description="oldest first: run id, state, created (UNIX s), operator, "
                                       "standards, parameters {S, k_f, b_f: value, std, unit}, approvals, drift")
    flagged: list[dict[str, Any]] = Field(description="values flagged as drift against earlier calibrations")
    certificates: list[dict[str, Any]] = Field(default_factory=list, description="issued certificates, oldest "
                                               "first: number, run_id, issued_at, approved_by, replaces, replaced_by")
    units: dict[str, str]
    trends: dict[str, Any] | None = Field(
        default=None, description="per parameter (S, k_f, b_f, f_0): the points, Shewhart and EWMA charts with "
        "their limits and false-alarm rate, as-found comparisons with the previous as-left value, drift risk at "
        "the next due date and the intervals methods A3, S2 and variables recommend (docs/batch.md)")
    out_of_control: list[dict[str, Any]] = Field(default_factory=list,
                                                 description="every chart's out-of-control points")
    hold: dict[str, Any] | None = Field(
        default=None, description="the station's check transducer out of control: transducer_id, since (UNIX s, "
        "its last good check), run_id, parameter, reason; approving and issuing the runs made since are refused "
        "(null: no hold)")


class PolicyIn(_In):
    """A transducer's policy: relative tolerances per parameter, the assigned interval, the check
    transducer mark."""

    tolerances: dict[str, float] = Field(default_factory=dict, max_length=4,
                                         description="relative, per parameter (S, k_f, b_f, f_0), e.g. {\"S\": 0.005}")
    interval_days: float | None = Field(default=None, ge=1, le=3660, description="assigned interval, d")
    check_standard: bool = Field(default=False, description="the transducer that stays on the rig")


class PolicyOut(PolicyIn):
    transducer_id: str
    updated: float = Field(description="UNIX s")
    updated_by: str


class AsLeftIn(_In):
    """An adjustment after a calibration: the value set in the user's instrument."""

    parameter: str = Field(pattern=r"^(S|k_f|b_f|f_0)$")
    value: float = Field(allow_inf_nan=False)
    unit: str = Field(max_length=32)
    note: str = Field(default="", max_length=1000)


class AsLeftOut(AsLeftIn):
    run_id: str
    transducer_id: str
    at: float = Field(description="UNIX s")
    by: str
