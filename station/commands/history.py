"""``station history TRANSDUCER``: a transducer's calibrations as the lab reads them: the control
charts of S, k_f, b_f and f_0 (Shewhart and EWMA) with their out-of-control points, the as-found
comparisons, the drift risk at the next due date and the interval each method recommends; also sets
the transducer's policy (tolerances, assigned interval, check transducer) and records an adjustment
(as-left value), both audited.  On the station's database directly, as ``station register``.

    station history TX5K-0001
    station history TX5K-0001 --tolerance S=0.005 --tolerance k_f=0.02 --interval-days 365
    station history TX5K-0001 --check-standard yes
    station history TX5K-0001 --as-left RUN_ID S=0.0020013 --note "gain set on the amplifier"
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from station.errors import BadInputError

UNITS = {"S": "V/N", "k_f": "N/m", "b_f": "N·s/m", "f_0": "Hz"}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("history", help="a transducer's control charts, as-found values, drift risk and intervals")
    p.add_argument("transducer", help="the transducer's id in the register")
    p.add_argument("--config", type=Path, default=None, help="station YAML (default config/sim-5kN.yaml)")
    p.add_argument("--json", action="store_true", help="print the history document as JSON")
    p.add_argument("--lambda", dest="lam", type=float, default=0.2, help="EWMA weight λ in (0, 1] (default 0.2)")
    p.add_argument("--L", dest="L", type=float, default=3.0, help="EWMA limit factor (default 3)")
    p.add_argument("--limit", type=int, default=500, help="the newest runs read (default 500)")
    p.add_argument("--tolerance", action="append", default=[], metavar="PARAM=REL",
                   help="set a relative tolerance, e.g. S=0.005 (repeatable)")
    p.add_argument("--interval-days", type=float, default=None, help="set the assigned calibration interval, d")
    p.add_argument("--check-standard", choices=("yes", "no"), default=None,
                   help="mark the transducer as the station's check transducer (or not)")
    p.add_argument("--as-left", nargs=2, metavar=("RUN", "PARAM=VALUE"),
                   help="record an adjustment after run RUN: the value set in the user's instrument")
    p.add_argument("--note", default="", help="a note with --as-left")
    p.set_defaults(handler=run)


def _pair(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    try:
        if not sep:
            raise ValueError
        return name.strip(), float(value)
    except ValueError:
        raise BadInputError(f"expected PARAM=NUMBER, got {text!r}") from None


def _fmt(x: Any) -> str:
    return f"{x:.6g}" if isinstance(x, (int, float)) else str(x)


def _text(doc: dict[str, Any]) -> str:
    lines = []
    trends = doc.get("trends") or {}
    pol = trends.get("policy") or {}
    lines.append(f"{len(doc['runs'])} runs; check transducer: {'yes' if pol.get('check_standard') else 'no'}; "
                 f"assigned interval: {_fmt(pol.get('interval_days')) + ' d' if pol.get('interval_days') else 'none'}")
    for name, p in (trends.get("parameters") or {}).items():
        unit = UNITS.get(name, p["unit"])
        lines.append(f"\n{name} ({unit}): {len(p['points'])} calibrations")
        for kind in ("shewhart", "ewma"):
            c = p.get(kind)
            if c:
                pts = c["points"]
                late = ", ".join(p["points"][i]["run_id"] for i in c["out_of_control"]) or "none"
                lines.append(f"  {kind}: centre {_fmt(c['centre'])}, limits {_fmt(pts[-1]['lower'])} .. "
                             f"{_fmt(pts[-1]['upper'])}, false-alarm rate {c['false_alarm_rate']:.2%} per point; "
                             f"out of control: {late}")
        if p.get("charts_note"):
            lines.append(f"  {p['charts_note']}")
        for f in p.get("as_found", [])[-3:]:
            tol = f", {'in' if f['in_tolerance'] else 'OUT OF'} tolerance" if "in_tolerance" in f else ""
            lines.append(f"  as found {f['run_id']}: {_fmt(f['difference'])} ± {_fmt(f['u'])} against the "
                         f"{f['as_left_source']} value of {f['previous_run_id']}{tol}")
        risk = p.get("drift_risk") or {}
        if "probability_out_of_tolerance" in risk:
            lines.append(f"  drift {_fmt(risk['slope_per_day'])} ± {_fmt(risk['u_slope_per_day'])} {unit}/d; "
                         "out of tolerance at the due date with probability "
                         f"{risk['probability_out_of_tolerance']:.1%}")
        for method, r in (p.get("intervals") or {}).items():
            if isinstance(r, dict) and isinstance(r.get("interval_days"), (int, float)):
                lines.append(f"  interval by {method}: {_fmt(r['interval_days'])} d (a recommendation)")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from station.commands.lab import cli_user, open_store
    from station.lab import history, policy, register

    if not 0 < args.lam <= 1 or not args.L > 0 or args.limit < 1:
        raise BadInputError("--lambda must lie in (0, 1], --L be > 0 and --limit >= 1")
    store, settings = open_store(args)
    try:
        register.seed(store, settings.config)
        t = register.transducer(store, args.transducer)
        if args.tolerance or args.interval_days is not None or args.check_standard is not None:
            old = policy.policy(store, t.id)
            tolerances = dict(old.tolerances) | dict(_pair(x) for x in args.tolerance)
            policy.put_policy(store, policy.Policy(
                t.id, tolerances, args.interval_days if args.interval_days is not None else old.interval_days,
                old.check_standard if args.check_standard is None else args.check_standard == "yes"), cli_user())
        if args.as_left:
            name, value = _pair(args.as_left[1])
            policy.record_as_left(store, policy.AsLeft(args.as_left[0], t.id, name, value, UNITS.get(name, ""),
                                                       args.note, time.time(), cli_user()))
        rows = history.runs_of(store, t.id, args.limit)
        ids = [r.id for r in rows]
        doc = history.history(rows, settings.recordings_dir, history.approvals(store, ids),
                              policy.policy(store, t.id), policy.as_left_of(store, t.id), lam=args.lam, L=args.L)
    finally:
        store.close()
    print(json.dumps(doc, indent=2, default=str) if args.json else _text(doc))
    return 0
