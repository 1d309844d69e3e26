"""The lab: /login, /logout, /me, /users, /register, /audit, /transducers/{id}/history,
/runs/{id}/approve and /runs/{id}/integrity."""

from __future__ import annotations

import logging
from dataclasses import asdict
from typing import Annotated

from fastapi import Depends, Path, Query, Request, Response

from station.api.deps import (
    SESSION_COOKIE,
    Admin,
    Approver,
    ManagerDep,
    Operator,
    PrincipalDep,
    Reader,
    RunDep,
    require,
)
from station.api.lab_schemas import (
    ID_PATTERN,
    ApprovalOut,
    ApproveIn,
    AsLeftIn,
    AsLeftOut,
    AuditEntryOut,
    AuditOut,
    ExceptionIn,
    HistoryOut,
    IntegrityOut,
    IntegrityReportOut,
    LockOut,
    LoginIn,
    MeOut,
    MountIn,
    PolicyIn,
    PolicyOut,
    RegisterOut,
    RoleOut,
    StandardIn,
    StandardOut,
    TokenIn,
    TokenOut,
    TokenRowOut,
    TransducerIn,
    TransducerOut,
    UserIn,
    UserOut,
    UserRowOut,
    UsersPolicyOut,
)
from station.api.routes import api_router
from station.api.routes.runs import BODY_ERRORS, E401, E403, E404, E409, E422
from station.api.schemas import ErrorOut
from station.lab import chain, register, users
from station.lab.users import NAME_PATTERN, Principal
from station.service.errors import RunStateError

log = logging.getLogger(__name__)
router = api_router(tags=["lab"])
EntryId = Annotated[str, Path(pattern=ID_PATTERN)]
UserName = Annotated[str, Path(pattern=NAME_PATTERN)]
SignedIn = Annotated[Principal, Depends(require(users.Permission.RUN))]  # any user of the lab (every role runs)


def _me(who: Principal | None) -> MeOut:
    if who is None:
        return MeOut(user=None)
    return MeOut(user=UserOut.model_validate(who.user.to_dict()), via=who.via, expires=who.expires)


# ---------------------------------------------------------------------------------------------- sessions
@router.post("/login", response_model=MeOut, responses={401: {"model": ErrorOut}, **E422, **BODY_ERRORS},
             summary="Log in on the page (sets an HttpOnly session cookie)")
async def login(body: LoginIn, manager: ManagerDep, response: Response, request: Request) -> MeOut:
    """A wrong name or password is refused alike (401), in the same time for any name.  After 5 failures
    in a row for a name or from an address, each further one locks it out for a growing time (2 s
    doubling to 15 min; refused, whatever the password, with the time it is lifted, after the same
    password check as any login; an administrator lifts it: `GET /logins/locks`).  The session expires
    after `lab.session_minutes`; the cookie is HttpOnly and SameSite=Strict."""
    session = await manager.lab.login(body.name, body.password, request.client.host if request.client else "")
    response.set_cookie(SESSION_COOKIE, session.text, max_age=int(session.minutes * 60), httponly=True,
                        samesite="strict", path="/")
    return MeOut(user=UserOut.model_validate(session.user.to_dict()), via="session", expires=session.expires)


@router.post("/logout", response_model=MeOut, responses={**E401, **BODY_ERRORS}, summary="End the page session")
async def logout(request: Request, manager: ManagerDep, response: Response) -> MeOut:
    session = request.cookies.get(SESSION_COOKIE)
    if session:
        await manager.lab.logout(session)
    response.delete_cookie(SESSION_COOKIE, path="/")
    return MeOut(user=None)


@router.get("/me", response_model=MeOut, responses={401: {"model": ErrorOut}}, summary="Who am I")
async def me(who: PrincipalDep) -> MeOut:
    """The logged-in user (or the token's); 401 with the reason for a wrong token or an expired
    session; `user: null` without credentials."""
    return _me(who)


# ---------------------------------------------------------------------------------------------- users
@router.get("/users", response_model=list[UserRowOut], responses={**E401, **E403}, summary="The users (admin)")
async def list_users(manager: ManagerDep, who: Admin) -> list[UserRowOut]:
    """Each user with the last change of the account (when, by whom; from the audit trail)."""
    return [UserRowOut.model_validate({**r.user.to_dict(), "changed": r.changed, "changed_by": r.changed_by})
            for r in await manager.lab.user_rows()]


@router.get("/users/policy", response_model=UsersPolicyOut, responses={**E401, **E403},
            summary="The roles and the rules for names and passwords (admin)")
async def users_policy(who: Admin) -> UsersPolicyOut:
    return UsersPolicyOut(roles=[RoleOut(name=r, permissions=sorted(str(p) for p in users.GRANTS[r]))
                                 for r in users.Role], min_password=users.MIN_PASSWORD, name_pattern=NAME_PATTERN)


@router.put("/users/{name}", response_model=UserOut, responses={**E401, **E403, **E409, **E422, **BODY_ERRORS},
            summary="Add or change a user (admin)")
async def put_user(name: UserName, body: UserIn, manager: ManagerDep, who: Admin) -> UserOut:
    """Role, password (hashed with scrypt; at least 10 characters), disabled (ends the user's sessions)."""
    u = await manager.lab.put_user(name, body.role, who, password=body.password, disabled=body.disabled)
    return UserOut.model_validate(u.to_dict())


@router.post("/users/{name}/tokens", response_model=TokenOut, status_code=201,
             responses={**E401, **E403, **E404, **E422, **BODY_ERRORS}, summary="Issue an API token for a user (admin)")
async def issue_token(name: UserName, body: TokenIn, manager: ManagerDep, who: Admin) -> TokenOut:
    text = await manager.lab.issue_token(name, body.label, who)
    return TokenOut(user=name, label=body.label, token=text)


@router.get("/logins/locks", response_model=list[LockOut], responses={**E401, **E403},
            summary="Names and client addresses locked out after failed logins (admin)")
async def login_locks(manager: ManagerDep, who: Admin) -> list[LockOut]:
    return [LockOut(**x) for x in manager.lab.locks()]


@router.delete("/logins/locks/{key}", response_model=list[LockOut], responses={**E401, **E403, **E404},
               summary="Lift a lock-out (admin)")
async def lift_lock(key: Annotated[str, Path(pattern=r"^(user|client):[^/]{1,128}$")], manager: ManagerDep,
                    who: Admin) -> list[LockOut]:
    return [LockOut(**x) for x in await manager.lab.lift_lock(key, who)]


@router.get("/tokens", response_model=list[TokenRowOut], responses={**E401, **E403, **E422},
            summary="The API tokens (never their text): the signed-in user's own; an admin's: all, or one user's")
async def list_tokens(manager: ManagerDep, who: SignedIn,
                      user: Annotated[str | None, Query(pattern=NAME_PATTERN)] = None) -> list[TokenRowOut]:
    return [TokenRowOut(**t) for t in await manager.lab.tokens(who, user)]


@router.delete("/tokens/{token_id}", response_model=TokenRowOut, responses={**E401, **E403, **E404, **E422},
               summary="Revoke an API token (the signed-in user's own; an admin: any)")
async def revoke_token(token_id: Annotated[str, Path(pattern=r"^[0-9a-f]{12}$")], manager: ManagerDep,
                       who: SignedIn) -> TokenRowOut:
    return TokenRowOut(**await manager.lab.revoke_token(token_id, who), created=None)


# ---------------------------------------------------------------------------------------------- register
def _standard_out(s: register.Standard, overdue: bool) -> StandardOut:
    return StandardOut(**s.to_dict(), overdue=overdue)


@router.get("/register", response_model=RegisterOut, dependencies=[Reader], responses=E401,
            summary="Transducers, reference standards, the mounted transducer")
async def get_register(manager: ManagerDep) -> RegisterOut:
    reg = await manager.lab.read_register()
    return RegisterOut(mounted=reg.mounted, transducers=[TransducerOut(**t.to_dict()) for t in reg.transducers],
                       standards=[_standard_out(x, overdue) for x, overdue in reg.standards],
                       overdue_policy=reg.overdue_policy)


@router.put("/register/transducers/{entry_id}", response_model=TransducerOut,
            responses={**E401, **E403, **E422, **BODY_ERRORS}, summary="Add or change a transducer (admin)")
async def put_transducer(entry_id: EntryId, body: TransducerIn, manager: ManagerDep, who: Admin) -> TransducerOut:
    t = register.Transducer(id=entry_id, **body.model_dump())
    return TransducerOut(**(await manager.lab.put_transducer(t, who)).to_dict())


@router.put("/register/standards/{entry_id}", response_model=StandardOut,
            responses={**E401, **E403, **E422, **BODY_ERRORS}, summary="Add or change a reference standard (admin)")
async def put_standard(entry_id: EntryId, body: StandardIn, manager: ManagerDep, who: Admin) -> StandardOut:
    st = register.Standard(id=entry_id, **body.model_dump())
    return _standard_out(*await manager.lab.put_standard(st, who))


@router.post("/register/mount", response_model=TransducerOut,
             responses={**E401, **E403, **E404, **E422, **BODY_ERRORS},
             summary="Choose the transducer mounted on the station")
async def mount(body: MountIn, manager: ManagerDep, who: Operator) -> TransducerOut:
    """The page's form defaults to it; a run may name any registered transducer."""
    return TransducerOut(**(await manager.lab.mount(body.transducer_id, who)).to_dict())


# ---------------------------------------------------------------------------------------------- audit
@router.get("/audit", response_model=AuditOut, dependencies=[Reader], responses={**E401, **E422},
            summary="The audit trail, newest first")
async def get_audit(manager: ManagerDep, target: Annotated[str | None, Query(max_length=128)] = None,
                    action: Annotated[str | None, Query(max_length=64, description="exact, or a prefix "
                                                        "ending in '.' (e.g. run.)")] = None,
                    who: Annotated[str | None, Query(max_length=64)] = None,
                    before_id: Annotated[int | None, Query(ge=1, le=2**63 - 1)] = None,
                    limit: Annotated[int, Query(ge=1, le=1000)] = 200) -> AuditOut:
    page = await manager.lab.audit_page(target=target, action=action, who=who, before_id=before_id,
                                        limit=limit)
    return AuditOut(count=len(page.entries), entries=[AuditEntryOut(**e.to_dict()) for e in page.entries],
                    broken=page.broken)


# ---------------------------------------------------------------------------------------------- runs
@router.post("/runs/{run_id}/approve", response_model=ApprovalOut, tags=["runs"],
             responses={**E401, **E403, **E404, **E409, **E422, **BODY_ERRORS},
             summary="Approve a completed run for its certificate (an approver, not who ran it)")
async def approve(run: RunDep, body: ApproveIn, manager: ManagerDep, who: Approver) -> ApprovalOut:
    """The second person's approval: refused (403) for the user who started the run, (409) for a
    run not completed or a recording whose SHA-256 differs from the one stored at closing."""
    return ApprovalOut(**await manager.approve(run.id, who.user, body.note))


@router.get("/integrity", response_model=IntegrityReportOut, dependencies=[Reader], responses={**E401, **E409},
            summary="Walk the audit chain and compare every file it vouches for")
async def station_integrity(manager: ManagerDep) -> IntegrityReportOut:
    """200 when every link of the audit trail's hash chain holds (or was reviewed by an administrator)
    and every recording, results file and certificate is as its entry recorded; 409 naming the first
    broken link and every file that differs otherwise."""
    out = await manager.integrity()
    if not out["ok"]:
        raise chain.ChainBrokenError(out["detail"])
    return IntegrityReportOut.model_validate(out)


@router.post("/integrity/exceptions", response_model=IntegrityReportOut,
             responses={**E401, **E403, **E409, **E422, **BODY_ERRORS},
             summary="Record a reviewed exception for a broken link of the chain (admin)")
async def record_exception(body: ExceptionIn, manager: ManagerDep, who: Admin) -> IntegrityReportOut:
    """The break stays listed with the exception's entry; it no longer degrades /health or blocks
    issuing.  409 when the chain has no broken link at that entry."""
    await manager.record_exception(who.user, body.entry, body.reason)
    out = await manager.integrity()
    return IntegrityReportOut.model_validate(out)


@router.get("/runs/{run_id}/integrity", response_model=IntegrityOut, tags=["runs"], dependencies=[Reader],
            responses={**E401, **E404, **E409}, summary="Check the recording against its SHA-256 stored at closing")
async def integrity(run: RunDep, manager: ManagerDep) -> IntegrityOut:
    if not run.recording:
        raise RunStateError(f"run {run.id} has no recording")
    sha = await manager.artifacts.verified(run)
    return IntegrityOut(run_id=run.id, recording=run.recording, sha256=sha, stored=run.recording_sha256 is not None)


@router.get("/transducers/{entry_id}/history", response_model=HistoryOut, dependencies=[Reader],
            responses={**E401, **E404}, summary="A transducer's runs, results, approvals, certificates and drift")
async def transducer_history(entry_id: EntryId, manager: ManagerDep,
                             limit: Annotated[int, Query(ge=1, le=2000)] = 500,
                             lam: Annotated[float, Query(gt=0, le=1, description="EWMA weight λ")] = 0.2,
                             L: Annotated[float, Query(gt=0, le=6, description="EWMA limit factor")] = 3.0,
                             ) -> HistoryOut:
    h = await manager.lab.transducer_history(entry_id, limit, lam, L)
    return HistoryOut(transducer=TransducerOut(**h.transducer.to_dict()), certificates=h.certificates,
                      hold=asdict(h.hold) if h.hold is not None else None, **h.document)


@router.put("/register/transducers/{entry_id}/policy", response_model=PolicyOut,
            responses={**E401, **E403, **E404, **E409, **E422, **BODY_ERRORS},
            summary="Set a transducer's tolerances, assigned interval and check-transducer mark (admin)")
async def put_policy(entry_id: EntryId, body: PolicyIn, manager: ManagerDep, who: Admin) -> PolicyOut:
    pol = await manager.lab.put_policy(entry_id, dict(body.tolerances), body.interval_days, body.check_standard, who)
    return PolicyOut(**pol.to_dict())


@router.post("/runs/{run_id}/as-left", response_model=AsLeftOut, tags=["runs"],
             responses={**E401, **E403, **E404, **E409, **E422, **BODY_ERRORS},
             summary="Record an adjustment after a calibration (the as-left value set in the user's instrument)")
async def as_left(run: RunDep, body: AsLeftIn, manager: ManagerDep, who: Approver) -> AsLeftOut:
    a = await manager.lab.record_as_left(run.id, run.transducer_id, body.parameter, body.value, body.unit,
                                         body.note, who)
    return AsLeftOut(**a.to_dict())
