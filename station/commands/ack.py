"""``station ack``: acknowledge a latched emergency stop on a running daemon (after the rig was checked).

Sends ``POST /stop/acknowledge`` with the token (``STATION_TOKEN``); the daemon resets the motor
controller's fault, records who acknowledged it and when, and runs may start again."""

from __future__ import annotations

import argparse
import json
import os
import sys

from station.errors import BadInputError, StationError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("ack", help="acknowledge a latched emergency stop on the station daemon")
    p.add_argument("--operator", default="", help="the operator at the rig, if not the token's user (recorded "
                   "in the note; who acknowledges is the token's user)")
    p.add_argument("--note", default="", help="what was checked (recorded)")
    p.add_argument("--url", default="http://127.0.0.1:8080", help="the daemon (default http://127.0.0.1:8080)")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    import urllib.error  # here: every other command's start goes without urllib's HTTP client
    import urllib.request

    token = os.environ.get("STATION_TOKEN", "").strip()
    if not token:
        raise BadInputError("set STATION_TOKEN to the daemon's token: acknowledging needs it")
    body = json.dumps({"operator": args.operator, "note": args.note}).encode()
    req = urllib.request.Request(f"{args.url.rstrip('/')}/stop/acknowledge", data=body, method="POST",
                                 headers={"Content-Type": "application/json", "Authorization": f"Bearer {token}"})
    try:
        with urllib.request.urlopen(req, timeout=15) as r:
            out = json.loads(r.read())
    except urllib.error.HTTPError as exc:
        detail = exc.read().decode(errors="replace")
        raise StationError(f"not acknowledged ({exc.code}): {detail}") from None
    except urllib.error.URLError as exc:
        raise StationError(f"cannot reach the daemon at {args.url}: {exc.reason}") from None
    if out["acknowledged"]:
        print(f"emergency stop acknowledged by {out['by']} at {out['at']}: {out['detail']}")
    else:
        print(f"no emergency stop was latched; {out['detail']}")
    sys.stdout.flush()
    return 0
