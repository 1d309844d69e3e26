"""``station stop``: the emergency stop of a running daemon, from a shell.

Sends ``POST /stop`` to the daemon's stop port (a listener of its own, see ``station serve``) and,
if that cannot be reached, to its main port.  No token is needed.  Prints what the drive reports;
the exit code is 0 when the drive, read back, reports standstill, 1 when it does not (use the
hardware emergency stop)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any
from urllib.parse import urlsplit

from station.errors import StationError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stop", help="emergency stop on the station daemon (its stop port, else its main port)")
    p.add_argument("--url", default="http://127.0.0.1:8080", help="the daemon (default http://127.0.0.1:8080)")
    p.add_argument("--stop-port", type=int, default=None,
                   help="the daemon's stop port (default: the --url port + 1, as service.stop_port's default)")
    p.set_defaults(handler=run)


def _post(url: str) -> dict[str, Any]:
    import urllib.request  # here: every other command's start goes without urllib's HTTP client

    req = urllib.request.Request(url, data=b"", method="POST")
    with urllib.request.urlopen(req, timeout=30) as r:  # the answer waits for the drive's read-back
        out: dict[str, Any] = json.loads(r.read())
    return out


def run(args: argparse.Namespace) -> int:
    import urllib.error

    base = args.url.rstrip("/")
    parts = urlsplit(base)
    port = args.stop_port if args.stop_port is not None else (parts.port or 80) + 1
    tried = []
    urls = (f"{parts.scheme}://{parts.hostname}:{port}/stop", f"{base}/stop")
    for url in urls:
        try:
            out = _post(url)
            break
        except urllib.error.HTTPError as exc:  # e.g. a name the stop port does not take: the main port next
            detail = exc.read().decode(errors="replace")
            if url == urls[-1]:
                raise StationError(f"the stop was refused ({exc.code}): {detail}; "
                                   "use the hardware emergency stop") from None
            print(f"the stop port refused the stop ({exc.code}: {detail}); trying the main port", file=sys.stderr)
        except (urllib.error.URLError, OSError) as exc:
            tried.append(f"{url}: {getattr(exc, 'reason', exc)}")
    else:
        raise StationError(f"cannot reach the daemon ({'; '.join(tried)}): use the hardware emergency stop")
    print(f"EMERGENCY STOP via {url}: {out['detail']}"
          + (f" (aborted runs: {', '.join(out['aborted_runs'])})" if out.get("aborted_runs") else ""))
    if not out.get("motor_stopped"):
        print("THE DRIVE DOES NOT REPORT STANDSTILL: use the hardware emergency stop")
    sys.stdout.flush()
    return 0 if out.get("motor_stopped") else 1
