"""``station users`` and ``station register``: the lab's users and register, on the station's
database directly (beside a running daemon too: SQLite in WAL mode).  Whoever runs these has the
database file in hand, i.e. administers the station; the audit trail names them ``cli:<login>``.

    station users add tina --role technician         (password from STATION_PASSWORD or asked)
    station users token ci-bot --label nightly        (prints the token once)
    station users tokens [ci-bot]                     (ids, labels, revoked or not; never the text)
    station users revoke 3f2a9c0d41be
    station users list
    station register list
    station register transducer TX5K-0002 --capacity-N 5000 --sensitivity-V-per-N 2e-6 --end-mass-kg 0.1
    station register standard LVDT-7 --kind displacement_sensor --certificate DKD-123 --issuer "DKD 12"
        --due-date 2027-06-30 --uncertainty 2e-7 --unit m
    station register mount TX5K-0002
"""

from __future__ import annotations

import argparse
import datetime as dt
import getpass
import json
import os
from pathlib import Path
from typing import Any

from station.errors import BadInputError

PASSWORD_ENV = "STATION_PASSWORD"


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, default=None, help="station YAML (default config/sim-5kN.yaml)")
    p.add_argument("--json", action="store_true", help="print JSON")


def register(sub: argparse._SubParsersAction) -> None:
    u = sub.add_parser("users", help="the station's users, roles and API tokens")
    us = u.add_subparsers(dest="action", required=True, metavar="ACTION")
    p = us.add_parser("list", help="list the users")
    _common(p)
    p = us.add_parser("add", help="add a user or change one's role or password")
    p.add_argument("name")
    p.add_argument("--role", required=True, choices=("technician", "approver", "admin"))
    p.add_argument("--no-password", action="store_true", help="keep the password (or none: token only)")
    p.add_argument("--disable", action="store_true", help="disable the user (ends their sessions)")
    _common(p)
    p = us.add_parser("token", help="issue an API token for a user (printed once)")
    p.add_argument("name")
    p.add_argument("--label", default="", help="what the token is for")
    _common(p)
    p = us.add_parser("tokens", help="list the API tokens (never their text), of one user or all")
    p.add_argument("name", nargs="?", default=None)
    _common(p)
    p = us.add_parser("revoke", help="revoke an API token by its id (as `tokens` lists it)")
    p.add_argument("token_id")
    _common(p)
    u.set_defaults(handler=run_users)

    r = sub.add_parser("register", help="the register: transducers, reference standards, the mounted one")
    rs = r.add_subparsers(dest="action", required=True, metavar="ACTION")
    p = rs.add_parser("list", help="list the register")
    _common(p)
    p = rs.add_parser("transducer", help="add or change a transducer")
    p.add_argument("id")
    p.add_argument("--capacity-N", type=float, required=True)
    p.add_argument("--sensitivity-V-per-N", type=float, required=True)
    p.add_argument("--end-mass-kg", type=float, default=None)
    p.add_argument("--end-mass-std-kg", type=float, default=None)
    p.add_argument("--type", default="")
    p.add_argument("--serial", default="")
    p.add_argument("--owner", default="")
    _common(p)
    p = rs.add_parser("standard", help="add or change a reference standard")
    p.add_argument("id")
    p.add_argument("--kind", required=True, choices=("displacement_sensor", "masses", "daq", "conditioner"))
    p.add_argument("--certificate", required=True, help="its calibration certificate's id")
    p.add_argument("--issuer", required=True)
    p.add_argument("--due-date", required=True, help="ISO date, e.g. 2027-06-30")
    p.add_argument("--uncertainty", type=float, required=True, help="the standard uncertainty it contributes")
    p.add_argument("--unit", required=True, help="the uncertainty's unit (m, kg, V/V, relative)")
    p.add_argument("--description", default="")
    p.add_argument("--not-in-use", action="store_true", help="registered, not used by default")
    _common(p)
    p = rs.add_parser("mount", help="choose the transducer mounted on the station")
    p.add_argument("id")
    _common(p)
    r.set_defaults(handler=run_register)


def open_store(args: argparse.Namespace) -> Any:
    from station.lab.store import Store
    from station.service.settings import load_settings

    settings = load_settings(args.config, sim=True)
    return Store(settings.database), settings


def cli_user() -> str:
    try:
        return f"cli:{getpass.getuser()}"
    except (KeyError, OSError):
        return "cli:unknown"


def _print(args: argparse.Namespace, doc: Any, text: str) -> None:
    print(json.dumps(doc, indent=2, default=str) if args.json else text)


def run_users(args: argparse.Namespace) -> int:
    from station.lab import users

    store, _ = open_store(args)
    try:
        if args.action == "list":
            us = users.users(store)
            _print(args, [u.to_dict() for u in us],
                   "\n".join(f"{u.name:20s} {u.role}{' (disabled)' if u.disabled else ''}" for u in us) or "no users")
        elif args.action == "add":
            password = None
            if not args.no_password:
                password = os.environ.get(PASSWORD_ENV) or getpass.getpass(f"password for {args.name}: ")
            u = users.put_user(store, args.name, users.Role(args.role), cli_user(), password=password,
                               disabled=args.disable)
            _print(args, u.to_dict(), f"user {u.name}: {u.role}{' (disabled)' if u.disabled else ''}")
        elif args.action == "tokens":
            ts = users.tokens(store, args.name)
            _print(args, ts, "\n".join(f"{t['id']}  {t['user']:16s} {t['label']:20s} "
                                       f"{'revoked' if t['revoked'] else 'valid'}" for t in ts) or "no tokens")
        elif args.action == "revoke":
            t = users.revoke_token(store, args.token_id, cli_user())
            _print(args, t, f"token {t['id']} of {t['user']} revoked")
        else:
            text = users.issue_token(store, args.name, args.label, cli_user())
            _print(args, {"user": args.name, "label": args.label, "token": text},
                   f"{text}\n(the token of {args.name}; shown once, only its hash is stored)")
    finally:
        store.close()
    return 0


def run_register(args: argparse.Namespace) -> int:
    from station.lab import register as reg

    store, settings = open_store(args)
    try:
        if args.action == "list":
            reg.seed(store, settings.config)
            today = dt.date.today()
            ts, ss, mounted = reg.transducers(store), reg.standards(store), reg.mounted(store)
            lines = [f"{'*' if t.id == mounted else ' '} {t.id:16s} {t.type} {t.serial} {t.capacity_N:g} N "
                     f"{t.owner}" for t in ts]
            lines += [f"  {s.id:16s} {s.kind:20s} {s.certificate_id} ({s.issuer}) due {s.due_date}"
                      f"{' OVERDUE' if s.overdue(today) else ''} u = {s.uncertainty:g} {s.uncertainty_unit}"
                      f"{'' if s.in_use else ' (not in use)'}" for s in ss]
            _print(args, {"mounted": mounted, "transducers": [t.to_dict() for t in ts],
                          "standards": [s.to_dict() for s in ss]}, "\n".join(lines))
        elif args.action == "transducer":
            from pydantic import ValidationError

            new = reg.Transducer(id=args.id, capacity_N=args.capacity_N, sensitivity_V_per_N=args.sensitivity_V_per_N,
                                 end_mass_kg=args.end_mass_kg, end_mass_std_kg=args.end_mass_std_kg, type=args.type,
                                 serial=args.serial, owner=args.owner)
            try:
                new.to_config()  # the configuration's bounds
            except ValidationError as exc:
                err = exc.errors()[0]
                raise BadInputError(f"{'.'.join(map(str, err['loc']))}: {err['msg']}") from None
            t = reg.put_transducer(store, new, cli_user())
            _print(args, t.to_dict(), f"transducer {t.id} registered")
        elif args.action == "standard":
            try:
                due = dt.date.fromisoformat(args.due_date).isoformat()
            except ValueError:
                raise BadInputError(f"--due-date {args.due_date!r}: expected an ISO date such as 2027-06-30") from None
            s = reg.put_standard(store, reg.Standard(
                id=args.id, kind=args.kind, certificate_id=args.certificate, issuer=args.issuer, due_date=due,
                uncertainty=args.uncertainty, uncertainty_unit=args.unit, description=args.description,
                in_use=not args.not_in_use), cli_user())
            _print(args, s.to_dict(), f"standard {s.id} registered (due {s.due_date})")
        else:
            t = reg.mount(store, args.id, cli_user())
            _print(args, t.to_dict(), f"transducer {t.id} mounted")
    finally:
        store.close()
    return 0
