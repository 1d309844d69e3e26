"""``station verify``: walk the station's audit chain and compare every recording, results file and
certificate it vouches for (exit 0 when everything holds, 1 naming the first broken link and every
file that differs); ``--except ENTRY --reason TEXT`` records an administrator's reviewed exception
for a broken link (an audit entry: the break stays listed, it no longer blocks issuing).

    station verify
    station verify --except 412 --reason "entry 412 was restored from the backup of 3 May; reviewed by QM"
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("verify", help="check the audit chain and every file it vouches for")
    p.add_argument("--config", type=Path, default=None, help="station YAML (default config/sim-5kN.yaml)")
    p.add_argument("--except", dest="exception", type=int, default=None, metavar="ENTRY",
                   help="record a reviewed exception for the broken link at this audit entry")
    p.add_argument("--reason", default="", help="what was reviewed (with --except)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    from station.commands.lab import cli_user, open_store
    from station.errors import BadInputError
    from station.lab import audit, chain

    store, settings = open_store(args)
    try:
        if args.exception is not None:
            if len(args.reason.strip()) < 10:
                raise BadInputError("--except needs --reason saying what was reviewed (10 characters at least)")
            with store.reading() as db:
                state = chain.verify_chain(db)
            if not any(b.id == args.exception for b in state.breaks):
                raise BadInputError(f"the audit chain has no broken link at entry {args.exception} "
                                    f"({state.describe()})")
            audit.append(store, cli_user(), audit.AUDIT_EXCEPTION, "audit",
                         {"entry": args.exception, "reason": args.reason.strip()})
        with store.reading() as db:
            out = chain.integrity_report(db, settings.recordings_dir)
    finally:
        store.close()
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        print(out["detail"].split("; ")[0])
        for b in out["breaks"]:
            print(f"  entry {b['id']}: {b['reason']}"
                  + (f" (reviewed: exception {b['excepted_by']})" if b["excepted_by"] else ""))
        for f in out["files"]:
            print(f"  file {f}")
        print("OK" if out["ok"] else "FAILED")
    return 0 if out["ok"] else 1
