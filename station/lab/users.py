"""Named users with roles, their credentials and sessions.

* Roles: ``technician`` (starts and aborts runs, acknowledges emergency stops), ``approver`` (also
  approves results for certificates, never their own runs), ``admin`` (also the register and the
  users; not approvals: a certificate's second signature is an approver's).
* Passwords are stored as scrypt hashes (``scrypt$n$r$p$salt$hash``, hex), never in clear.
* API tokens (scripts, CI) are bound to a user and stored as their SHA-256; the text is shown once.
* Page sessions: a random id in an HttpOnly cookie, stored as its SHA-256, expiring after
  ``lab.session_minutes``.
Every change is audited in the same transaction.
"""

from __future__ import annotations

import enum
import hashlib
import hmac
import re
import secrets
import time
from dataclasses import dataclass
from typing import Any

from station.errors import StationError
from station.lab import audit
from station.lab.store import Store

SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**14, 8, 1  # 16 MiB, ~50 ms per check on this machine's class
MIN_PASSWORD = 10
NAME_PATTERN = r"^[a-z][a-z0-9_.\-]{0,31}$"


class Role(enum.StrEnum):
    TECHNICIAN = "technician"
    APPROVER = "approver"
    ADMIN = "admin"


class Permission(enum.StrEnum):
    RUN = "run"  # start, abort runs, acknowledge the emergency stop, compute analyses
    APPROVE = "approve"  # approve a result for a certificate (a run someone else started)
    ADMIN = "admin"  # the register, the users


GRANTS: dict[Role, frozenset[Permission]] = {
    Role.TECHNICIAN: frozenset({Permission.RUN}),
    Role.APPROVER: frozenset({Permission.RUN, Permission.APPROVE}),
    Role.ADMIN: frozenset({Permission.RUN, Permission.ADMIN}),
}


class AuthError(StationError):
    """Credentials refused (401): the message says why and what to do."""


class ForbiddenError(StationError):
    """Authenticated, but the role does not allow it (403)."""


class UserError(StationError):
    """A change of the users refused (bad name, short password)."""


class UnknownUserError(UserError):
    pass


@dataclass(frozen=True)
class User:
    name: str
    role: Role
    disabled: bool = False

    def may(self, perm: Permission) -> bool:
        return not self.disabled and perm in GRANTS[self.role]

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "role": str(self.role), "disabled": self.disabled,
                "permissions": sorted(str(p) for p in GRANTS[self.role])}


@dataclass(frozen=True)
class Principal:
    """Who makes a request: the user and how they authenticated (``token``, ``session``)."""

    user: User
    via: str
    expires: float | None = None  # a session's end, UNIX s

    @property
    def name(self) -> str:
        return self.user.name


# ---------------------------------------------------------------------------------------------- hashes
def hash_password(password: str, n: int = SCRYPT_N) -> str:
    """The stored form of ``password``: scrypt with a new salt at cost ``n`` (the product's SCRYPT_N;
    a simulated station's may be lower: ``simulation.password_cost_log2``).  The cost is part of the hash:
    a check uses the one stored."""
    salt = secrets.token_bytes(16)
    h = hashlib.scrypt(password.encode(), salt=salt, n=n, r=SCRYPT_R, p=SCRYPT_P, dklen=32)
    return f"scrypt${n}${SCRYPT_R}${SCRYPT_P}${salt.hex()}${h.hex()}"


def check_password(password: str, stored: str) -> bool:
    try:
        kind, n, r, p, salt, h = stored.split("$")
        if kind != "scrypt":
            return False
        got = hashlib.scrypt(password.encode(), salt=bytes.fromhex(salt), n=int(n), r=int(r), p=int(p),
                             dklen=len(bytes.fromhex(h)), maxmem=2**26)
    except ValueError:
        return False
    return hmac.compare_digest(got, bytes.fromhex(h))


def secret_hash(secret: str) -> str:
    """The stored form of a token or session id (random, long: one SHA-256 suffices)."""
    return hashlib.sha256(secret.encode()).hexdigest()


# ---------------------------------------------------------------------------------------------- users
def _user(row: dict[str, Any]) -> User:
    return User(row["name"], Role(row["role"]), bool(row["disabled"]))


def users(store: Store) -> list[User]:
    return [_user(r) for r in store.query("SELECT * FROM users ORDER BY name")]


def last_changes(store: Store) -> dict[str, tuple[float, str]]:
    """Each user's last change from the audit trail (``user.changed``): name -> (UNIX s, by whom)."""
    rows = store.query("SELECT a.target, a.at, a.who FROM audit a JOIN (SELECT max(id) AS id FROM audit "
                       "WHERE action = ? GROUP BY target) m ON a.id = m.id", (audit.USER_CHANGED,))
    return {str(r["target"]).removeprefix("user:"): (float(r["at"]), str(r["who"])) for r in rows}


def get_user(store: Store, name: str) -> User | None:
    rows = store.query("SELECT * FROM users WHERE name = ?", (name,))
    return _user(rows[0]) if rows else None


def _check_new(name: str, password: str | None) -> None:
    import re

    if not re.match(NAME_PATTERN, name):
        raise UserError(f"user name {name[:40]!r}: expected lower-case letters, digits, '_', '.', '-', "
                        "starting with a letter, at most 32 characters")
    if password is not None and len(password) < MIN_PASSWORD:
        raise UserError(f"the password must have at least {MIN_PASSWORD} characters")


def put_user(store: Store, name: str, role: Role, by: str, *, password: str | None = None,
             disabled: bool = False, n: int = SCRYPT_N) -> User:
    """Add a user or change one's role, password (when given, hashed at scrypt cost ``n``) or disabled flag."""
    _check_new(name, password)
    hashed = hash_password(password, n) if password is not None else None
    now = time.time()
    with store.transaction() as db:
        old = db.execute("SELECT role, disabled FROM users WHERE name = ?", (name,)).fetchone()
        if old is None:
            db.execute("INSERT INTO users (name, role, password, created, created_by, disabled) "
                       "VALUES (?, ?, ?, ?, ?, ?)", (name, str(role), hashed or "", now, by, int(disabled)))
        else:
            db.execute("UPDATE users SET role = ?, disabled = ? WHERE name = ?", (str(role), int(disabled), name))
            if hashed is not None:
                db.execute("UPDATE users SET password = ? WHERE name = ?", (hashed, name))
        if disabled or hashed is not None:  # a disabled user's sessions, or all after a new password, end now
            db.execute("UPDATE sessions SET ended = ? WHERE user = ? AND ended IS NULL", (now, name))
        audit.record(db, by, audit.USER_CHANGED, f"user:{name}",
                     {"role": str(role), "disabled": disabled, "password_changed": hashed is not None,
                      "before": None if old is None else {"role": old[0], "disabled": bool(old[1])}}, at=now)
    return User(name, role, disabled)


def ensure_user(store: Store, name: str, role: Role) -> User:
    """The user ``name`` (created with ``role`` and no password if missing: it cannot log in on the
    page until one is set)."""
    u = get_user(store, name)
    return u if u is not None else put_user(store, name, role, audit.SYSTEM)


# ---------------------------------------------------------------------------------------------- tokens
def issue_token(store: Store, name: str, label: str, by: str) -> str:
    """A new API token for user ``name``; the text is returned once, only its hash is stored."""
    if get_user(store, name) is None:
        raise UnknownUserError(f"no user {name!r}")
    text = "sct_" + secrets.token_urlsafe(24)
    with store.transaction() as db:
        db.execute("INSERT INTO tokens (hash, user, label, created) VALUES (?, ?, ?, ?)",
                   (secret_hash(text), name, label, time.time()))
        audit.record(db, by, audit.TOKEN_ISSUED, f"user:{name}", {"label": label})
    return text


def tokens(store: Store, name: str | None = None) -> list[dict[str, Any]]:
    """The API tokens (never their text): id (the first 12 characters of the hash), user, label,
    created, revoked (UNIX s or None)."""
    q = "SELECT hash, user, label, created, revoked FROM tokens" + (" WHERE user = ?" if name else "") + \
        " ORDER BY created"
    return [{"id": r["hash"][:12], "user": r["user"], "label": r["label"], "created": r["created"],
             "revoked": r["revoked"]} for r in store.query(q, (name,) if name else ())]


def revoke_token(store: Store, token_id: str, by: str, owner: str | None = None) -> dict[str, Any]:
    """Revoke a token by its id (:func:`tokens`); audited.  UnknownUserError when no live token has
    it (or none of ``owner``'s, when given: a user revokes only their own)."""
    if not re.fullmatch(r"[0-9a-f]{12}", token_id):
        raise UserError(f"not a token id: {token_id[:20]!r} (12 hex digits, as GET /tokens lists them)")
    now = time.time()
    with store.transaction() as db:
        rows = db.execute("SELECT hash, user, label FROM tokens WHERE substr(hash, 1, 12) = ? AND revoked IS NULL",
                          (token_id,)).fetchall()
        if len(rows) != 1 or (owner is not None and rows[0][1] != owner):
            raise UnknownUserError(f"no live token {token_id}" + (f" of user {owner}" if owner is not None else ""))
        db.execute("UPDATE tokens SET revoked = ? WHERE hash = ?", (now, rows[0][0]))
        audit.record(db, by, audit.TOKEN_REVOKED, f"user:{rows[0][1]}", {"token": token_id, "label": rows[0][2]},
                     at=now)
    return {"id": token_id, "user": rows[0][1], "label": rows[0][2], "revoked": now}


def user_of_token(store: Store, text: str) -> User | None:
    rows = store.query("SELECT u.* FROM tokens t JOIN users u ON u.name = t.user WHERE t.hash = ? AND "
                       "t.revoked IS NULL", (secret_hash(text),))
    return _user(rows[0]) if rows else None


# ---------------------------------------------------------------------------------------------- sessions
# a password hash nobody has, per scrypt cost: checked for unknown, disabled and password-less names
_DUMMY: dict[int, str] = {}


def _dummy_hash(n: int = SCRYPT_N) -> str:
    if n not in _DUMMY:
        _DUMMY[n] = hash_password(secrets.token_urlsafe(16), n)
    return _DUMMY[n]


def login_candidate(store: Store, name: str, n: int = SCRYPT_N) -> tuple[User | None, str]:
    """(the user who may log in with a password, the hash to check): for an unknown, disabled or
    password-less name (None, a hash nobody has, at the cost ``n`` the station stores passwords
    with), so that the check costs the same one scrypt whatever the name is (no name can be told
    from another by the time a refusal takes)."""
    rows = store.query("SELECT * FROM users WHERE name = ?", (name,)) if re.match(NAME_PATTERN, name) else []
    if not rows or not rows[0]["password"] or rows[0]["disabled"]:
        return None, _dummy_hash(n)
    return _user(rows[0]), str(rows[0]["password"])


def check_login(store: Store, name: str, password: str, n: int = SCRYPT_N) -> User | None:
    """The user if the name and password are right; None for a wrong name or password alike (one
    scrypt check in every case: :func:`login_candidate`, ``n`` its cost).  The daemon splits it: the
    look-up in its read pool, the scrypt check in the login pool (``service/logins.py``)."""
    user, stored = login_candidate(store, name, n)
    ok = check_password(password, stored)
    return user if ok and user is not None else None


REFUSED = "wrong user name or password (ask an administrator if you have none or forgot it)"


def refuse_login(store: Store, name: str, client: str = "", *, locked: bool = False) -> None:
    """Audit a refused login: the name only when it is a valid user name (a password typed into the
    name field is never stored), the client's address, and whether a lock-out refused it."""
    valid = bool(re.match(NAME_PATTERN, name))
    shown = name if valid else "?"
    audit.append(store, shown, audit.LOGIN_REFUSED, f"user:{shown}",
                 {"client": client, **({"locked": True} if locked else {}),
                  **({} if valid else {"name": "not a valid user name (not stored)"})})


def keep_lock(store: Store, key: str, failures: int, locked_until: float) -> None:
    """Keep a login lock-out (``service/logins.LoginThrottle``) across restarts; failures 0 forgets it."""
    with store.transaction() as db:
        if failures:
            db.execute("INSERT OR REPLACE INTO login_locks (key, failures, locked_until) VALUES (?, ?, ?)",
                       (key, int(failures), float(locked_until)))
        else:
            db.execute("DELETE FROM login_locks WHERE key = ?", (key,))


def kept_locks(store: Store) -> list[tuple[str, int, float]]:
    """The login lock-outs kept: (key, failures, locked until in UNIX s), also those run out (their
    count still doubles the next lock-out)."""
    return [(r["key"], int(r["failures"]), float(r["locked_until"]))
            for r in store.query("SELECT key, failures, locked_until FROM login_locks")]


def open_session(store: Store, user: User, minutes: float) -> tuple[str, float]:
    """A new page session for ``user``: its cookie text and its end (UNIX s); audited."""
    text = secrets.token_urlsafe(32)
    now = time.time()
    expires = now + minutes * 60.0
    with store.transaction() as db:
        db.execute("INSERT INTO sessions (hash, user, created, expires) VALUES (?, ?, ?, ?)",
                   (secret_hash(text), user.name, now, expires))
        audit.record(db, user.name, audit.LOGIN, f"user:{user.name}", {"expires": expires}, at=now)
    return text, expires


def login(store: Store, name: str, password: str, minutes: float) -> tuple[str, User, float]:
    """Check the password and open a session (both in the caller's thread: for the command line and
    tests; the daemon checks in its read pool and writes through its writer).  AuthError if refused."""
    user = check_login(store, name, password)
    if user is None:
        refuse_login(store, name)
        raise AuthError(REFUSED)
    text, expires = open_session(store, user, minutes)
    return text, user, expires


def session_user(store: Store, text: str, now: float | None = None) -> Principal:
    """The user of a page session; AuthError saying why not (unknown, ended, expired)."""
    rows = store.query("SELECT s.expires, s.ended, u.* FROM sessions s JOIN users u ON u.name = s.user "
                       "WHERE s.hash = ?", (secret_hash(text),))
    if not rows:
        raise AuthError("not logged in (unknown session): log in again")
    r = rows[0]
    if r["ended"] is not None:
        raise AuthError("your session was ended (logged out or the user was disabled): log in again")
    now = time.time() if now is None else now
    if r["expires"] <= now:
        at = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(r["expires"]))
        raise AuthError(f"your session expired at {at}: log in again")
    return Principal(_user(r), "session", r["expires"])


def logout(store: Store, text: str) -> str | None:
    """End a session; returns its user (None: no such session)."""
    rows = store.query("SELECT user FROM sessions WHERE hash = ? AND ended IS NULL", (secret_hash(text),))
    if not rows:
        return None
    with store.transaction() as db:
        db.execute("UPDATE sessions SET ended = ? WHERE hash = ?", (time.time(), secret_hash(text)))
        audit.record(db, rows[0]["user"], audit.LOGOUT, f"user:{rows[0]['user']}")
    return str(rows[0]["user"])
