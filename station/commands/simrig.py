"""``station sim-rig``: start the simulated rig (motor-controller and DAQ-bridge emulators) and serve."""

from __future__ import annotations

import argparse
import threading
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim-rig", help="run the simulated rig: Modbus motor controller + DAQ bridge on ptys")
    p.add_argument("--config", type=Path, default=None,
                   help="station YAML whose simulation section sets the physics (default: 5 kN preset)")
    p.add_argument("--modbus-port", type=int, default=0, help="Modbus TCP port on 127.0.0.1 (0 = any free)")
    p.add_argument("--seed", type=int, default=0, help="noise seed of the synthesised signals")
    p.add_argument("--profile", default=None, help="drive profile the motor emulator behaves as (a shipped "
                   "name or a YAML path; default: the config's rig.motor.profile, else sinecal-crank)")
    p.add_argument("--crank-radius", type=float, default=None,
                   help="crank radius in m (default: the first plan step's, else 0.01)")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from drivers.motor.errors import RegisterMapError
    from drivers.motor.profile import load_profile
    from drivers.rig.presets import paper_5kN_physics
    from drivers.sim.rig import SimRig
    from station.errors import ConfigError

    physics = paper_5kN_physics()
    radius = 0.01
    profile_name = args.profile
    if args.config is not None:
        from station.config import load_config, to_rig_physics

        cfg = load_config(args.config)
        physics = to_rig_physics(cfg)
        radius = cfg.plan.steps[0].crank_radius_m
        profile_name = profile_name or cfg.rig.motor.profile
    if args.crank_radius is not None:
        radius = args.crank_radius
    try:
        profile = load_profile(profile_name)
    except RegisterMapError as exc:
        raise ConfigError(f"--profile: {exc}") from None
    with SimRig(physics=physics, seed=args.seed, modbus_port=args.modbus_port, crank_radius_m=radius,
                profile=profile) as rig:
        a = rig.addresses
        print(f"motor controller  Modbus TCP  {a.modbus_tcp_url}  (drive profile {profile.name})", flush=True)
        unit = rig.map.transport.unit_id
        print(f"motor controller  Modbus RTU  {a.modbus_rtu}  (115200 Bd 8N2 on the pty, unit {unit})", flush=True)
        print(f"DAQ bridge        serial      {a.daq}", flush=True)
        print("Ctrl-C to stop", flush=True)
        threading.Event().wait()
    return 0
