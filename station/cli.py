"""The ``station`` console script: one entry point, sub-commands registered by their modules."""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import sys
from collections.abc import Sequence

from station import __version__
from station.commands import COMMAND_MODULES
from station.errors import StationError


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every registered sub-command."""
    parser = argparse.ArgumentParser(prog="station", description="sinecal calibration station")
    parser.add_argument("--version", action="version", version=f"sinecal {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def _single_threaded_blas() -> None:
    """One BLAS/OpenMP thread unless the user chose otherwise: the station's linear algebra is many
    small problems, for which a BLAS thread pool costs more than it gains (``bench/cli.py``: identify
    0.67 s against 0.92 s of CPU on 2 cores).  Effective because the commands load numpy only when
    they run, after this; worker processes inherit it."""
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the exit code (2 for bad input, 1 for other failures)."""
    _single_threaded_blas()
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        return int(args.handler(args) or 0)
    except StationError as exc:
        print(f"station {args.command}: error: {exc}", file=sys.stderr)
        if getattr(args, "json", False) is True:  # a refusal under --json is a JSON document too
            print(json.dumps({"error": {"command": args.command, "message": str(exc), "kind": type(exc).__name__,
                                        "exit_code": exc.exit_code}}, indent=2))
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"station {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a driver's or the system's failure: one clear line, the traceback with -v
        logging.getLogger("station.cli").debug("station %s failed", args.command, exc_info=True)
        message = f"{type(exc).__name__}: {exc}"
        hint = "" if args.verbose else " (run with -v for the details)"
        print(f"station {args.command}: error: {message}{hint}", file=sys.stderr)
        if getattr(args, "json", False) is True:
            print(json.dumps({"error": {"command": args.command, "message": message, "kind": type(exc).__name__,
                                        "exit_code": 1}}, indent=2))
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
