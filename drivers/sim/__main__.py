"""``python -m drivers.sim``: run the simulated rig until stdin closes (or Ctrl-C).

Prints one line with the addresses (JSON with ``--json``) and then serves.  Lines on stdin control
the emulators from another process (one JSON line answers each on stdout):

- ``status``: the motor's true state, ``{"status": {"speed_hz", "enabled", "fault_code", "estop",
  "watchdog_refreshes", "radius_m", "t_monotonic"}}`` (the refreshes the drive took since it
  started; the crank radius the signals are synthesised with, m);
- ``ignore-stops on`` / ``ignore-stops off``: the drive takes every command but keeps turning when
  told to stop (see ``MotorModel.ignore_stops``), ``{"ignore_stops": true}``;
- ``radius R``: change the crank radius to R m as a motorised eccentric does (waits up to 3 s for
  standstill), ``{"radius_m": R}`` or ``{"error": ...}``;
- ``load B``: synthesise other physics from now on (B: a :class:`~drivers.rig.params.RigPhysics`
  pickled and base64-encoded, as :meth:`SimRigProcess.load_physics` sends it; the daemon that
  started this process is the only writer of its stdin), ``{"loaded": true}``.

The same ``status`` and ``radius R`` lines (only those) are answered on a Unix socket too, one
line each way per connection, whose path the addresses line gives as ``control``: the rig process,
which the daemon starts apart from this one, changes the crank radius there during its runs.

With ``--commands`` every command the motor controller takes (each register written, except the
watchdog refreshes) is printed as ``{"command": name, "value": v, "t_monotonic": t}``, with
``time.monotonic()`` of this process at the moment the write was applied (one clock for every
process on the machine).
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import contextlib
import json
import logging
import os
import pickle
import socket
import sys
import tempfile
import threading
import time
from typing import Any

from drivers.motor.errors import RegisterMapError
from drivers.motor.profile import load_profile
from drivers.sim.daq_source import RigSource
from drivers.sim.process import addresses_json
from drivers.sim.rig import SimRig

_out = threading.Lock()
_commands = threading.Lock()  # one command at a time, from stdin or the control socket
CONTROL_LINE = 200  # bytes of a control socket's line, at most


def _say(obj: dict[str, Any] | str) -> None:
    with _out:
        sys.stdout.write((obj if isinstance(obj, str) else json.dumps(obj)) + "\n")
        sys.stdout.flush()


def _command(rig: SimRig, line: str) -> dict[str, Any]:
    words = line.split()
    if words == ["status"]:
        s = rig.motor.snapshot()
        return {"status": {"speed_hz": s.speed_hz, "enabled": s.enabled, "fault_code": s.fault_code,
                           "estop": s.estop, "watchdog_refreshes": rig.motor.watchdog_refreshes,
                           "radius_m": rig.source.crank_radius_m if isinstance(rig.source, RigSource) else None,
                           "t_monotonic": time.monotonic()}}
    if len(words) == 2 and words[0] == "ignore-stops" and words[1] in ("on", "off"):
        rig.motor.ignore_stops(words[1] == "on")
        return {"ignore_stops": words[1] == "on"}
    try:
        if len(words) == 2 and words[0] == "radius":
            asyncio.run(rig.change_crank_radius(float(words[1])))
            return {"radius_m": float(words[1])}
        if len(words) == 2 and words[0] == "load":
            rig.load_physics(pickle.loads(base64.b64decode(words[1])))
            return {"loaded": True}
    except (RuntimeError, ValueError, pickle.UnpicklingError) as exc:
        return {"error": f"{words[0]}: {exc}"}
    return {"error": f"unknown command {line[:80]!r}; expected 'status', 'ignore-stops on|off', 'radius R' "
                     "or 'load B'"}


def _serve_control(rig: SimRig, server: socket.socket) -> None:
    """The control socket: ``status`` and ``radius R`` (never ``load``: no pickle from a socket)."""
    while True:
        try:
            conn, _ = server.accept()
        except OSError:
            return
        threading.Thread(target=_control_connection, args=(rig, conn), name="sim-control", daemon=True).start()


def _control_connection(rig: SimRig, conn: socket.socket) -> None:
    with conn, conn.makefile("rwb") as f:
        line = f.readline(CONTROL_LINE).decode("ascii", "replace").strip()
        words = line.split()
        if words[:1] in (["status"], ["radius"]):
            with _commands:
                reply = _command(rig, line)
        else:
            reply = {"error": f"unknown command {line[:80]!r} on the control socket; expected 'status' or 'radius R'"}
        with contextlib.suppress(OSError):
            f.write((json.dumps(reply) + "\n").encode())
            f.flush()


HARDWARE_NICE = -10  # the emulators' priority where the OS gives it (every thread they start inherits it)


def _as_hardware() -> None:
    """Raise this process's priority (nice -10), every thread's, before it starts its own: a drive and a DAQ bridge
    are hardware of their own, answering in milliseconds whatever load the station's computer
    carries, and the emulators stand in for them.  At normal priority a loaded machine (tests in
    parallel, both cores busy) delays a reply beyond the drive's reply time-out, a failure no real
    drive would cause.  Refused (no privilege): said on stderr, and the emulators run as they are."""
    try:  # every thread there is (numerical libraries start theirs at import), and what they start
        tids = [int(t) for t in os.listdir("/proc/self/task")] if os.path.isdir("/proc/self/task") else [0]
        for tid in tids:
            with contextlib.suppress(ProcessLookupError):  # a thread that ended meanwhile
                os.setpriority(os.PRIO_PROCESS, tid, HARDWARE_NICE)
    except OSError as exc:
        logging.getLogger("drivers.sim").warning(
            "simulated rig: priority nice %d refused (%s); it runs at nice %d, and a loaded machine may "
            "delay its replies", HARDWARE_NICE, exc.strerror, os.getpriority(os.PRIO_PROCESS, 0))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m drivers.sim", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--modbus-port", type=int, default=0, help="TCP port on 127.0.0.1 (0 = any free port)")
    ap.add_argument("--crank-radius", type=float, default=0.01, help="crank radius in m")
    ap.add_argument("--json", action="store_true", help="print the addresses as one JSON line")
    ap.add_argument("--profile", default=None, help="drive profile the motor emulator behaves as (shipped name "
                    "or YAML path; default sinecal-crank)")
    ap.add_argument("--daq-link", default="uart", choices=("uart", "usb-cdc"),
                    help="the link kind the DAQ bridge emulator reports")
    ap.add_argument("--commands", action="store_true",
                    help="print every command the motor controller takes as a JSON line")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    _as_hardware()
    try:
        profile = load_profile(args.profile)
    except RegisterMapError as exc:
        ap.error(str(exc))
    with SimRig(seed=args.seed, modbus_port=args.modbus_port, crank_radius_m=args.crank_radius,
                profile=profile, daq_link=args.daq_link) as rig:
        if args.commands:
            def seen(name: str, value: float, t: float) -> None:
                if name != "watchdog":
                    _say({"command": name, "value": value, "t_monotonic": t})
            rig.image.observers.append(seen)
        if isinstance(rig.source, RigSource):
            rig.source.warm()  # numba's kernels before the addresses: the first CONF is answered at once
        folder = tempfile.mkdtemp(prefix="sinecal-sim-")
        control = os.path.join(folder, "control")
        server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        server.bind(control)
        os.chmod(control, 0o600)
        server.listen(4)
        threading.Thread(target=_serve_control, args=(rig, server), name="sim-control-accept", daemon=True).start()
        _say(addresses_json(rig.addresses, control))
        try:
            with contextlib.suppress(KeyboardInterrupt):
                for line in sys.stdin:  # ends at EOF
                    if line.strip():
                        with _commands:
                            reply = _command(rig, line.strip())
                        _say(reply)
        finally:
            server.close()
            with contextlib.suppress(OSError):
                os.unlink(control)
                os.rmdir(folder)
    return 0


if __name__ == "__main__":
    sys.exit(main())
