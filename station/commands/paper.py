"""``station paper``: regenerate the paper's tables and figures next to ours (station.paper)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("paper", help="reproduce the paper's Table 1, noise study and Section 5 protocol")
    p.add_argument("--out", type=Path, default=Path("recordings/paper"), help="folder for the PNG figures")
    p.add_argument("--quick", action="store_true", help="fewer iterations and seeds (seconds, not minutes)")
    p.add_argument("--seed", type=int, default=0, help="first seed of every random process")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from station.paper import format_report, run_paper

    report = run_paper(args.out, quick=args.quick, seed=args.seed)
    print(json.dumps(report, indent=2) if args.json else format_report(report))
    return 0
