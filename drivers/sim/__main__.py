"""``python -m drivers.sim``: run the simulated rig until stdin closes (or Ctrl-C).

Prints one line with the addresses (JSON with ``--json``) and then serves.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys

from drivers.sim.rig import SimRig, addresses_json


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m drivers.sim", description=__doc__)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--modbus-port", type=int, default=0, help="TCP port on 127.0.0.1 (0 = any free port)")
    ap.add_argument("--crank-radius", type=float, default=0.01, help="crank radius in m")
    ap.add_argument("--json", action="store_true", help="print the addresses as one JSON line")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    with SimRig(seed=args.seed, modbus_port=args.modbus_port, crank_radius_m=args.crank_radius) as rig:
        sys.stdout.write(addresses_json(rig.addresses) + "\n")
        sys.stdout.flush()
        with contextlib.suppress(KeyboardInterrupt):
            sys.stdin.read()  # returns at EOF
    return 0


if __name__ == "__main__":
    sys.exit(main())
