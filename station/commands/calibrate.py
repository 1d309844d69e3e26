"""``station calibrate``: a whole calibration run through the real drivers, then identification."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from station.errors import BadInputError, StationError

if TYPE_CHECKING:
    from station.run.procedure import Progress


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate", help="run a stepped-sine calibration and identify the transducer")
    p.add_argument("--sim", action="store_true", help="start the simulated rig (emulators) and use it")
    p.add_argument("--config", type=Path, default=None, help="station YAML (default config/sim-5kN.yaml)")
    p.add_argument("--steps", type=str, default=None,
                   help="crank frequencies in Hz, e.g. 3,5,8 (radius chosen within the limits); "
                        "default: the configured plan")
    p.add_argument("--out", type=Path, default=None, help="recordings folder (default: the config's)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(handler=run)


def _freqs(text: str | None) -> list[float] | None:
    if not text:
        return None
    try:
        vals = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise BadInputError(f"--steps: comma-separated frequencies in Hz expected, got {text!r}") from None
    if not vals:
        raise BadInputError("--steps: at least one frequency expected")
    return vals


class _Bar:
    """One progress line per step on stderr (``sample_rate_hz``: the DAQ's, to show samples as seconds)."""

    def __init__(self, sample_rate_hz: float) -> None:
        self._fs = sample_rate_hz
        self._last = 0.0
        self._step: int | None = None

    def __call__(self, p: Progress) -> None:
        now = time.monotonic()
        if p.step != self._step and self._step is not None:
            sys.stderr.write("\n")
        if p.step == self._step and now - self._last < 0.25 and p.step_state != "done":
            return
        self._step, self._last = p.step, now
        width = 30
        fill = int(width * p.fraction)
        step = "-" if p.step is None else f"{p.step + 1}/{p.n_steps}"
        sys.stderr.write(f"\r[{'#' * fill}{'.' * (width - fill)}] step {step} {p.step_state:<9} "
                         f"{p.samples / self._fs:7.1f} s  lost {p.lost_samples}  {p.message[:40]:<40}")
        sys.stderr.flush()


def run(args: argparse.Namespace) -> int:
    import asyncio  # here: every other command's start goes without asyncio (registering imports this module)

    from drivers.daq.link import DaqLinkError
    from drivers.motor.errors import MotorCommunicationError
    from station.commands.identify import format_text
    from station.config import default_config_path, load_config
    from station.run.calibrate import run_and_identify
    from station.run.request import default_request
    from station.service.instance import InstanceLock

    cfg = load_config(args.config or default_config_path())
    if not args.sim and cfg.simulation is not None:
        print("note: the configuration has a simulation section but --sim was not given; "
              "connecting to the real devices of cfg.devices", file=sys.stderr)
    request = default_request(cfg, _freqs(args.steps))
    out = args.out or Path(cfg.station.recordings_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BadInputError(f"recordings folder {out}: cannot create it ({exc.strerror})") from None
    with InstanceLock.acquire(out, "station calibrate"):  # not beside a daemon's live run
        try:
            result = asyncio.run(run_and_identify(cfg, request, out, sim=args.sim,
                                                  on_progress=_Bar(cfg.daq.sample_rate_hz)))
        except (MotorCommunicationError, DaqLinkError) as exc:
            dev = cfg.devices
            where = (f"the motor controller at {dev.motor_url}" if isinstance(exc, MotorCommunicationError)
                     else f"the DAQ bridge at {dev.daq_port}")
            raise StationError(f"cannot reach {where} ({exc}); check that it is powered and connected "
                               "(devices.* in the configuration), or add --sim for the simulated rig") from None
    sys.stderr.write("\n")
    if args.json:
        print(json.dumps(result.to_json(), indent=2))
    else:
        print(result.header())
        if result.identification is not None:
            print(format_text(result.identification))
    return 0 if result.outcome.exit_status == "completed" else 1
