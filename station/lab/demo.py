"""The simulated station's demonstration users: a technician and an approver, so that a newcomer
can log in on the page at once (``station serve --sim``; never on a real rig).

Each start of the simulated station gives them new random passwords, printed once in its log; a
user of either name that someone else made is left alone."""

from __future__ import annotations

import secrets
from dataclasses import dataclass

from station.lab import users
from station.lab.store import Store

DEMO_BY = "station serve --sim"  # who the audit trail says made them
DEMO_USERS: tuple[tuple[str, users.Role], ...] = (("technician", users.Role.TECHNICIAN),
                                                  ("approver", users.Role.APPROVER))


@dataclass(frozen=True)
class DemoUser:
    name: str
    role: users.Role
    password: str | None  # None: a user of this name exists that the simulation did not make


def demo_users(store: Store, n: int = users.SCRYPT_N) -> list[DemoUser]:
    """Make (or give new passwords to) the demonstration users (hashed at scrypt cost ``n``); their
    passwords, once."""
    out = []
    for name, role in DEMO_USERS:
        rows = store.query("SELECT created_by FROM users WHERE name = ?", (name,))
        if rows and rows[0]["created_by"] != DEMO_BY:
            out.append(DemoUser(name, role, None))
            continue
        password = "-".join(secrets.token_hex(3) for _ in range(3))  # 20 characters, easy to type
        users.put_user(store, name, role, DEMO_BY, password=password, n=n)
        out.append(DemoUser(name, role, password))
    return out
