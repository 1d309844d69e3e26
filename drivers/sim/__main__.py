"""``python -m drivers.sim``: run the simulated rig until stdin closes (or Ctrl-C).

Prints one line with the addresses (JSON with ``--json``) and then serves.  Lines on stdin control
the emulators from another process (one JSON line answers each on stdout):

- ``status``: the motor's true state, ``{"status": {"speed_hz", "enabled", "fault_code", "estop",
  "t_monotonic"}}``;
- ``ignore-stops on`` / ``ignore-stops off``: the drive takes every command but keeps turning when
  told to stop (see ``MotorModel.ignore_stops``), ``{"ignore_stops": true}``.

With ``--commands`` every command the motor controller takes (each register written, except the
watchdog refreshes) is printed as ``{"command": name, "value": v, "t_monotonic": t}``, with
``time.monotonic()`` of this process at the moment the write was applied (one clock for every
process on the machine).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import sys
import threading
import time
from typing import Any

from drivers.motor.errors import RegisterMapError
from drivers.motor.profile import load_profile
from drivers.sim.rig import SimRig, addresses_json

_out = threading.Lock()


def _say(obj: dict[str, Any] | str) -> None:
    with _out:
        sys.stdout.write((obj if isinstance(obj, str) else json.dumps(obj)) + "\n")
        sys.stdout.flush()


def _command(rig: SimRig, line: str) -> dict[str, Any]:
    words = line.split()
    if words == ["status"]:
        s = rig.motor.snapshot()
        return {"status": {"speed_hz": s.speed_hz, "enabled": s.enabled, "fault_code": s.fault_code,
                           "estop": s.estop, "t_monotonic": time.monotonic()}}
    if len(words) == 2 and words[0] == "ignore-stops" and words[1] in ("on", "off"):
        rig.motor.ignore_stops(words[1] == "on")
        return {"ignore_stops": words[1] == "on"}
    return {"error": f"unknown command {line[:80]!r}; expected 'status' or 'ignore-stops on|off'"}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m drivers.sim", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--modbus-port", type=int, default=0, help="TCP port on 127.0.0.1 (0 = any free port)")
    ap.add_argument("--crank-radius", type=float, default=0.01, help="crank radius in m")
    ap.add_argument("--json", action="store_true", help="print the addresses as one JSON line")
    ap.add_argument("--profile", default=None, help="drive profile the motor emulator behaves as (shipped name "
                    "or YAML path; default sinecal-crank)")
    ap.add_argument("--commands", action="store_true",
                    help="print every command the motor controller takes as a JSON line")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    try:
        profile = load_profile(args.profile)
    except RegisterMapError as exc:
        ap.error(str(exc))
    with SimRig(seed=args.seed, modbus_port=args.modbus_port, crank_radius_m=args.crank_radius,
                profile=profile) as rig:
        if args.commands:
            def seen(name: str, value: float, t: float) -> None:
                if name != "watchdog":
                    _say({"command": name, "value": value, "t_monotonic": t})
            rig.image.observers.append(seen)
        _say(addresses_json(rig.addresses))
        with contextlib.suppress(KeyboardInterrupt):
            for line in sys.stdin:  # ends at EOF
                if line.strip():
                    _say(_command(rig, line.strip()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
