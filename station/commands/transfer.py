"""``station import`` and ``station export``: the sinecal-csv interchange format; ``station export
--results``: the results as CSV and an Excel workbook."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("import", help="turn a run recorded elsewhere (RUN.yaml + CSV) into a recording")
    p.add_argument("run_yaml", type=Path, metavar="RUN.yaml")
    p.add_argument("--out", type=Path, default=Path("recordings"), help="output folder")
    p.set_defaults(handler=_import)
    e = sub.add_parser("export", help="write a recording's steps as RUN.yaml + CSV (--results: its parameters "
                       "and S_dyn(f) as CSV and an Excel workbook)")
    e.add_argument("recording", type=Path, metavar="RECORDING")
    e.add_argument("--out", type=Path, default=Path("."), help="folder that receives <run_id>/ (--results: the "
                   "files <stem>.parameters.csv, <stem>.sdyn.csv, <stem>.results.xlsx)")
    e.add_argument("--results", action="store_true", help="export the stored results (parameters with their "
                   "uncertainties, S_dyn(f)) as CSV and .xlsx instead of the steps")
    e.set_defaults(handler=_export)


def _import(args: argparse.Namespace) -> int:
    from station.interchange import import_run

    print(import_run(args.run_yaml, args.out))
    return 0


def _export(args: argparse.Namespace) -> int:
    if args.results:
        from station.report.export import write_exports

        for path in write_exports(args.recording, args.out):
            print(path)
        return 0
    from station.interchange import export_run

    print(export_run(args.recording, args.out))
    return 0
