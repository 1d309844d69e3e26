"""Calibration runs on the simulated rig for the tests of the run procedure: one function runs a
procedure and fires a fault (or any action) once at a chosen moment of its progress."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path
from typing import Any

from drivers.sim.clock import VirtualClock
from station.config import StationConfig, parse_config
from station.run.procedure import Procedure, Progress
from station.run.request import RunRequest, StepSpec, plan_run
from station.run.rig import ConnectedRig, connect
from tests.conftest import station_dict


def small_config(**plan: Any) -> dict[str, Any]:
    """The shipped configuration with a short settle (0.2 s), record (1 s) and a 50 Hz/s crank ramp
    (``plan``: other values)."""
    return station_dict(**{"settle_s": 0.2, "record_s": 1.0, "acceleration_hz_per_s": 50.0, **plan})


CFG = parse_config(small_config())  # the runs' default configuration
STEPS = [StepSpec(crank_frequency_hz=f, crank_radius_m=0.001) for f in (10.0, 20.0, 30.0)]


def run_with(tmp_path: Path, when: Callable[[Progress], bool] | None, act: Callable[[ConnectedRig, Procedure], None],
             steps: list[StepSpec] = STEPS, *, wire: bool = False,
             cfg: StationConfig = CFG, clock: VirtualClock | None = None,
             ) -> tuple[object, ConnectedRig, dict[str, float]]:
    """Run a procedure on the simulated rig; ``act`` fires once when ``when(progress)`` is true.
    Returns the outcome, the rig (closed) and the motor state seen right after the run.
    ``wire``: over Modbus TCP and a pty in real time; else in-process on a virtual clock (``clock``,
    a new one by default)."""
    plan = plan_run(cfg, RunRequest(transducer_id=cfg.transducer.id, top_mass_kg=cfg.rig.top_mass_kg, steps=steps))

    async def go() -> tuple[object, ConnectedRig, dict[str, float]]:
        async with connect(plan.config, sim=True, first_radius_m=steps[0].crank_radius_m,
                           sim_clock=None if wire else clock or VirtualClock()) as rig:
            fired = False
            proc: Procedure

            def progress(p: Progress) -> None:
                nonlocal fired
                if not fired and when is not None and when(p):
                    fired = True
                    act(rig, proc)
            proc = Procedure(plan, rig, tmp_path, on_progress=progress)
            outcome = await proc.execute()
            assert fired or when is None, "the fault was never injected"
            # the motor after the run, from the emulator's own model (no driver in between)
            deadline = rig.clock.monotonic() + 10
            while rig.sim.motor.speed_hz() != 0 and rig.clock.monotonic() < deadline:
                await rig.clock.asleep(0.05)
            snap = rig.sim.motor.snapshot()
            motor = {"speed_hz": rig.sim.motor.speed_hz(), "enabled": float(snap.enabled)}
            return outcome, rig, motor
    return asyncio.run(go())
