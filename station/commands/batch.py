"""``station batch``: ask the station daemon for the check transducer's short calibration, then
re-identify the recordings in scope and write each transducer's parameters over time with drift and
control charts (docs/batch.md)."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from station.batch.summary import K_DEFAULT, MIN_HISTORY, PARAMS, write_summaries
from station.errors import BadInputError
from station.ident.names import METHODS, MODELS

if TYPE_CHECKING:
    from station.config import StationConfig

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("batch", help="re-identify recordings and track each transducer's parameters (drift)")
    p.add_argument("--config", type=Path, default=None, help="station YAML (default config/sim-5kN.yaml)")
    p.add_argument("--recordings", type=Path, default=None,
                   help="recordings folder (default: the config's station.recordings_dir)")
    p.add_argument("--since", default=None, help="only runs started at or after this ISO 8601 date/time (UTC)")
    p.add_argument("--transducer", default=None, metavar="ID", help="only runs of this transducer")
    p.add_argument("--executor", default="local", metavar="local|dask://HOST:PORT",
                   help="local process pool (default) or a Dask distributed scheduler")
    p.add_argument("--workers", type=int, default=2, help="processes of the local pool (default 2)")
    p.add_argument("--method", choices=METHODS, default=None, help="identification method (default: each method the "
                   "recording's identification.methods lists, one drift series per method)")
    p.add_argument("--model", choices=MODELS, default=None, help="model (default: the method's own, auto for fd)")
    p.add_argument("--summary-dir", type=Path, default=None,
                   help="where <transducer>.json/.csv go (default: <recordings>/summary)")
    p.add_argument("--store", action="store_true", help="also store each result in its recording")
    p.add_argument("--k", type=float, default=K_DEFAULT, help=f"drift threshold in combined standard "
                   f"uncertainties (default {K_DEFAULT:g})")
    p.add_argument("--min-history", type=int, default=MIN_HISTORY,
                   help=f"earlier runs needed before a value is judged (default {MIN_HISTORY})")
    bar = p.add_mutually_exclusive_group()
    bar.add_argument("--progress", dest="progress", action="store_true", default=None,
                     help="progress bar on stderr (default: when stderr is a terminal)")
    bar.add_argument("--no-progress", dest="progress", action="store_false")
    p.add_argument("--no-check", dest="check", action="store_false",
                   help="do not ask the station daemon for the check transducer's run first (default: when the "
                   "register marks a check transducer, its short calibration runs before the re-identification)")
    p.add_argument("--station", default=None, metavar="URL",
                   help="the station daemon (default: batch.station_url, else http://service.host:service.port)")
    p.add_argument("--json", action="store_true", help="print the items and drift flags as JSON")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from station.batch.runner import run_batch
    from station.batch.scope import parse_when, select_recordings
    from station.config import default_config_path, load_config

    if args.workers < 1:
        raise BadInputError(f"--workers: at least 1 expected, got {args.workers}")
    if not args.k > 0 or args.min_history < 1:
        raise BadInputError("--k must be > 0 and --min-history >= 1")
    if args.station is not None and not args.station.startswith(("http://", "https://")):
        raise BadInputError(f"--station: http://HOST:PORT or https://HOST:PORT expected, got {args.station!r}")
    since = parse_when(args.since) if args.since else None
    cfg = load_config(args.config or default_config_path()) if args.recordings is None or args.config else None
    folder = Path(cfg.station.recordings_dir) if args.recordings is None and cfg is not None else args.recordings
    checks, check_notes = check_first(cfg, args) if args.check and cfg is not None else ([], [])
    paths, notes = select_recordings(folder, since=since, transducer=args.transducer)
    progress = sys.stderr.isatty() if args.progress is None else args.progress
    items = run_batch(paths, workers=args.workers, executor=args.executor, progress=progress,
                      method=args.method, model=args.model, store=args.store)
    out = args.summary_dir or folder / "summary"
    docs = write_summaries(items, out, k=args.k, min_history=args.min_history,
                           check_runs=checks) if items or checks else {}
    failed = [it for it in items if not it.ok]
    missed = [c for c in checks if c["status"] != "completed"]
    if args.json:
        print(json.dumps({"recordings": len(paths), "skipped": notes, "summary_dir": str(out),
                          "items": [it.to_dict() for it in items], "check_runs": checks, "check_notes": check_notes,
                          "flagged": {tx: d["flagged"] for tx, d in docs.items()}}, indent=2))
    else:
        for n in check_notes:
            print(f"check run: {n}")
        for c in checks:
            word = "CHECK RUN" if c["status"] == "completed" else f"CHECK RUN {c['status'].upper()}"
            print(f"{word} {c['transducer_id']}: {c['detail']}")
            if c.get("hold"):
                print(f"  HOLD: {c['hold']}")
        print(f"{len(paths)} recordings in scope in {folder}, {len(notes)} left out, {len(failed)} failed")
        for n in notes:
            print(f"  skipped: {n}")
        for it in failed:
            print(f"  failed: {it.path.name}: {it.error}")
        for tx, d in docs.items():
            last = next((r for r in reversed(d["runs"]) if r["status"] == "ok"), None)
            vals = "" if last is None else ", ".join(
                f"{n} {last['parameters'][n]['value']:.6g} {u}" for n, u in PARAMS
                if (last["parameters"].get(n) or {}).get("value") is not None)
            print(f"{tx}: {len(d['runs'])} runs; latest {vals}; summary {out / tx}.json/.csv")
            for f in d["flagged"]:
                print(f"  DRIFT {f['parameter']} in run {f['run_id']}: {f['value']:.6g}, history mean "
                      f"{f['history_mean']:.6g}, deviation {f['deviation']:.3g} > {args.k:g} x {f['u_c']:.3g}")
            for o in d.get("out_of_control", []):
                print(f"  OUT OF CONTROL {o['parameter']} ({o['method']}, {o['chart']} chart) in run {o['run_id']}")
    for tx, d in docs.items():
        if d["flagged"]:
            log.warning("batch: drift flagged for %s (%d value(s))", tx, len(d["flagged"]))
    for c in missed:
        log.warning("batch: the check run of %s was %s: %s", c["transducer_id"], c["status"], c["detail"])
    return 1 if failed or missed else 0


def check_first(cfg: StationConfig, args: argparse.Namespace) -> tuple[list[dict[str, Any]], list[str]]:
    """The check transducers the register marks (the station's database), each one's short
    calibration asked of the daemon (``station.batch.check``) and, after it, whether the check
    transducer now holds certificates (``station.lab.history.check_hold``).  Returns the findings
    (``CheckRun`` as dicts with ``hold``) and notes (why no check run was asked for)."""
    import asyncio
    import sqlite3

    from station.batch.check import check_runs
    from station.lab import history, policy
    from station.service.store import Store

    rec_dir = Path(cfg.station.recordings_dir).expanduser()
    db = Path(cfg.service.database).expanduser()
    db = db if db.is_absolute() else rec_dir / db
    if not db.is_file():
        return [], [f"no station database at {db}: no check transducer is marked"]
    try:
        store = Store(db)
        try:
            marked = policy.check_transducers(store)
        finally:
            store.close()  # not held open while the check runs (up to batch.check_timeout_s)
    except sqlite3.Error as exc:
        log.warning("batch: the station database %s could not be read (%s): no check run", db, exc)
        return [], [f"the station database {db} could not be read ({exc}): no check run was asked for"]
    if not marked:
        return [], ["the register marks no check transducer"]
    if args.station:
        cfg = cfg.model_copy(update={"batch": cfg.batch.model_copy(update={"station_url": args.station})})
    token = os.environ.get("STATION_TOKEN", "").strip() or cfg.service.token
    found = asyncio.run(check_runs(cfg, marked, token))
    try:
        store = Store(db)
        try:
            hold = history.check_hold(store, rec_dir)
        finally:
            store.close()
    except sqlite3.Error as exc:
        log.warning("batch: whether the check transducer holds certificates could not be read (%s)", exc)
        hold = None
    return [{**c.to_dict(), "hold": hold.reason if hold is not None and hold.transducer_id == c.transducer_id
             else None} for c in found], []
