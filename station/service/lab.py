"""The lab's use cases: logging in and out, the users and their API tokens, the lock-outs after
failed logins, the register of transducers and reference standards, the audit trail, a transducer's
history, its policy and the as-left values recorded after an adjustment.

Each reads or writes the lab's records through the database's pools (:class:`DbAccess`: reads in
the read pool, writes through the one writer) and returns the lab's own types; the API's routes
only translate them (``station.api.routes.lab``)."""

from __future__ import annotations

import asyncio
import datetime as dt
import logging
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from station.lab import audit, chain, history, policy, register, users
from station.lab.history import CheckHold
from station.lab.store import Store
from station.lab.users import NAME_PATTERN, Principal, User
from station.service.artifacts import Artifacts
from station.service.db import DbAccess
from station.service.logins import LoginThrottle, PasswordPool

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Session:
    """A page session just opened: its user, the cookie's text, its end (s since the epoch) and its
    length in minutes."""

    user: User
    text: str
    expires: float
    minutes: float


@dataclass(frozen=True)
class UserRow:
    """A user with the last change of the account (when, s since the epoch, and by whom; from the
    audit trail)."""

    user: User
    changed: float | None
    changed_by: str | None


@dataclass(frozen=True)
class Register:
    """The register: the mounted transducer's id, the transducers, the standards (each with whether
    its calibration is overdue today) and what an overdue standard does (``lab.overdue_standards``)."""

    mounted: str | None
    transducers: list[register.Transducer]
    standards: list[tuple[register.Standard, bool]]
    overdue_policy: str


@dataclass(frozen=True)
class AuditPage:
    """Audit entries, newest first, and the ids among them whose chain link is broken."""

    entries: list[audit.AuditEntry]
    broken: list[int]


@dataclass(frozen=True)
class TransducerHistory:
    """A transducer, its history document (``station.lab.history.history``), the certificates issued
    for it and a check transducer's hold, if one is out of control."""

    transducer: register.Transducer
    document: dict[str, Any]
    certificates: list[dict[str, Any]]
    hold: CheckHold | None


class LabService:
    """The lab's use cases on the daemon's database, for its lifetime."""

    def __init__(self, db: DbAccess, logins: LoginThrottle, passwords: PasswordPool, session_minutes: float,
                 overdue_policy: str, recordings_dir: Path, artifacts: Artifacts, *,
                 password_n: int = users.SCRYPT_N) -> None:
        """``password_n``: the scrypt cost of the passwords stored (ServiceSettings.password_n)."""
        self.db = db
        self.password_n = password_n
        self.logins = logins
        self.passwords = passwords
        self.session_minutes = session_minutes
        self.overdue_policy = overdue_policy
        self.recordings_dir = recordings_dir
        self.artifacts = artifacts

    # ------------------------------------------------------------------ sessions
    async def login(self, name: str, password: str, client: str) -> Session:
        """A session for ``name``, or :class:`users.AuthError`.  A wrong name or password is refused
        alike, in the same time for any name; after repeated failures a name or an address is locked
        out (:class:`LoginThrottle`), refused whatever the password after the same password check as
        any login.  Every login, refused or not, awaits one write (the session, or the refusal's
        audit entry) through the writer."""
        user_key = f"user:{name}" if re.match(NAME_PATTERN, name) else "user:?"
        keys = [user_key, f"client:{client}"]
        why = self.logins.refusal(keys)
        # admitted first: a login beyond the pool's bound reads nothing (the reads in flight are
        # everybody's); the scrypt check (~0.1 s) in the login pool, never in the read pool
        async with self.passwords.admitted() as admitted:
            if not admitted:
                raise users.AuthError("too many logins at once: try again in a moment")
            candidate, stored = await self.db.read(lambda s: users.login_candidate(s, name, self.password_n))
            ok = await self.passwords.check(users.check_password, password, stored)
        # locked out: the same work done (no lock-out told by its time), the answer unused
        user = candidate if ok and why is None else None
        if user is None:
            for key, seconds in [] if why is not None else self.logins.failed(keys):  # counted before any wait
                log.warning("login lock-out: %s for %.0f s after repeated failures", key, seconds)
                self.db.post(lambda s, k=key, t=seconds: audit.append(  # type: ignore[misc]
                    s, audit.SYSTEM, audit.LOGIN_LOCKED, k, {"seconds": t}))
            await self.db.call(lambda s: users.refuse_login(s, name, client, locked=why is not None))
            raise users.AuthError(why or users.REFUSED)
        self.logins.succeeded(user_key)
        minutes = self.session_minutes
        text, expires = await self.db.call(lambda s: users.open_session(s, user, minutes))
        return Session(user, text, expires, minutes)

    async def logout(self, session: str) -> None:
        await self.db.call(lambda s: users.logout(s, session))

    # ------------------------------------------------------------------ users, tokens, lock-outs
    async def user_rows(self) -> list[UserRow]:
        def read(s: Store) -> list[UserRow]:
            changed = users.last_changes(s)
            return [UserRow(u, *changed.get(u.name, (None, None))) for u in users.users(s)]
        return await self.db.read(read)

    async def put_user(self, name: str, role: users.Role, by: Principal, *, password: str | None,
                       disabled: bool) -> User:
        return await self.db.call(lambda s: users.put_user(s, name, role, by.name, password=password,
                                                           disabled=disabled, n=self.password_n))

    async def issue_token(self, name: str, label: str, by: Principal) -> str:
        """A new API token's text for user ``name`` (shown once; only its hash is kept)."""
        return await self.db.call(lambda s: users.issue_token(s, name, label, by.name))

    def locks(self) -> list[dict[str, Any]]:
        return self.logins.locks()

    async def lift_lock(self, key: str, by: Principal) -> list[dict[str, Any]]:
        """Lift a lock-out (audited); :class:`users.UnknownUserError` for an unknown key."""
        if not self.logins.lift(key):
            raise users.UnknownUserError(f"no lock-out or failure count for {key}")
        await self.db.call(lambda s: audit.append(s, by.name, audit.LOGIN_LOCKED, key, {"lifted": True}))
        return self.logins.locks()

    async def tokens(self, who: Principal, user: str | None) -> list[dict[str, Any]]:
        """The API tokens (never their text): the user's own; an administrator's: all, or ``user``'s."""
        if not who.user.may(users.Permission.ADMIN):
            if user not in (None, who.name):
                raise users.ForbiddenError(f"user {who.name} ({who.user.role}) sees only their own tokens; an "
                                           "admin sees every user's")
            user = who.name
        return await self.db.read(lambda s: users.tokens(s, user))

    async def revoke_token(self, token_id: str, who: Principal) -> dict[str, Any]:
        """Revoke a token: the user's own; an administrator's: any."""
        owner = None if who.user.may(users.Permission.ADMIN) else who.name
        return await self.db.call(lambda s: users.revoke_token(s, token_id, who.name, owner))

    # ------------------------------------------------------------------ the register
    async def read_register(self) -> Register:
        def read(s: Store) -> Register:
            today = dt.date.today()
            return Register(register.mounted(s), register.transducers(s),
                            [(x, x.overdue(today)) for x in register.standards(s)], self.overdue_policy)
        return await self.db.read(read)

    async def put_transducer(self, t: register.Transducer, by: Principal) -> register.Transducer:
        return await self.db.call(lambda s: register.put_transducer(s, t, by.name))

    async def put_standard(self, st: register.Standard, by: Principal) -> tuple[register.Standard, bool]:
        """The standard as stored, and whether its calibration is overdue today."""
        out = await self.db.call(lambda s: register.put_standard(s, st, by.name))
        return out, out.overdue(dt.date.today())

    async def mount(self, transducer_id: str, by: Principal) -> register.Transducer:
        return await self.db.call(lambda s: register.mount(s, transducer_id, by.name))

    # ------------------------------------------------------------------ the audit trail
    async def audit_page(self, *, target: str | None, action: str | None, who: str | None, before_id: int | None,
                    limit: int) -> AuditPage:
        def read(s: Store) -> AuditPage:
            rows = audit.entries(s, target=target, action=action, who=who, before_id=before_id, limit=limit)
            with s.reading() as db:
                return AuditPage(rows, chain.broken_among(db, [e.id for e in rows]))
        return await self.db.read(read)

    # ------------------------------------------------------------------ a transducer's history and policy
    async def transducer_history(self, entry_id: str, limit: int, lam: float, L: float) -> TransducerHistory:
        """The transducer's runs, results, approvals, certificates and drift (EWMA weight ``lam``,
        limit factor ``L``); :class:`register.UnknownEntryError` for an unknown transducer."""
        t, rows = await self.db.read(lambda s: (register.transducer(s, entry_id), history.runs_of(s, entry_id, limit)))
        ids = [r.id for r in rows]
        approved, pol, left = await self.db.read(lambda s: (history.approvals(s, ids), policy.policy(s, entry_id),
                                                            policy.as_left_of(s, entry_id)))
        doc = await asyncio.to_thread(history.history, rows, self.recordings_dir, approved, pol, left, lam=lam, L=L)
        hold = await self.db.read(lambda s: history.check_hold(s, self.recordings_dir))
        certs = await self.artifacts.certificates(entry_id)
        return TransducerHistory(t, doc, certs, hold)

    async def put_policy(self, entry_id: str, tolerances: dict[str, float], interval_days: float | None,
                         check_standard: bool, by: Principal) -> policy.Policy:
        def write(s: Store) -> policy.Policy:
            register.transducer(s, entry_id)  # 404 for an unknown one
            return policy.put_policy(s, policy.Policy(entry_id, tolerances, interval_days, check_standard), by.name)
        return await self.db.call(write)

    async def record_as_left(self, run_id: str, transducer_id: str, parameter: str, value: float, unit: str,
                             note: str, by: Principal) -> policy.AsLeft:
        """An adjustment after a calibration: the as-left value set in the user's instrument."""
        a = policy.AsLeft(run_id, transducer_id, parameter, value, unit, note, time.time(), by.name)
        return await self.db.call(lambda s: policy.record_as_left(s, a))
