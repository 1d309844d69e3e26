"""``station simulate``: write a recording of a whole stepped-sine run straight from the physics."""

from __future__ import annotations

import argparse
from pathlib import Path

from station.errors import BadInputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="write a simulated recording of the configured plan")
    p.add_argument("--config", type=Path, default=None, help="station YAML (default config/sim-5kN.yaml)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: the config's)")
    p.add_argument("--seed", type=int, default=None, help="noise seed (default: the config's)")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from station.config import default_config_path, load_config
    from station.simulate import simulate_run

    if args.seed is not None and args.seed < 0:
        raise BadInputError(f"--seed: a non-negative integer expected, got {args.seed}")
    cfg = load_config(args.config or default_config_path())
    out = args.out or Path(cfg.station.recordings_dir)
    path = simulate_run(cfg, out, seed=args.seed)
    print(path)
    return 0
