"""A calibration from request to identified parameters: plan, run, process, identify."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers.clock import Clock
from station.config import StationConfig
from station.ident.response.checked import checked_response
from station.ident.result import IdentificationResult
from station.recording import read_recording
from station.run.methods import identify_all, identify_primary
from station.run.procedure import Procedure, Progress, RunOutcome
from station.run.processing import process_recording
from station.run.request import RunRequest, plan_run
from station.run.rig import connect

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CalibrationResult:
    outcome: RunOutcome
    identification: IdentificationResult | None

    def to_json(self) -> dict[str, Any]:
        """``station identify --json`` plus ``recording``, ``lost_samples``, ``exit_status``, ``reason``."""
        base: dict[str, Any] = self.identification.to_dict() if self.identification else {}
        return {**base, "recording": str(self.outcome.path), "lost_samples": self.outcome.lost_samples,
                "exit_status": self.outcome.exit_status, "reason": self.outcome.reason}

    def header(self) -> str:
        return "\n".join([f"recording: {self.outcome.path}", f"exit status: {self.outcome.exit_status}"
                          + (f" ({self.outcome.reason})" if self.outcome.reason else ""),
                          f"lost samples: {self.outcome.lost_samples}"])


def process_and_identify(path: Path, *, secondaries: bool = True) -> IdentificationResult:
    """After a run: H(f) per step (``processed/steps``), then the listed identifications
    (``identification.methods`` of the recording's configuration, ``station.run.methods``): the
    primary's result (``results/identify_<method>_<model>``), stored beside the recording with every
    method's outcome (``results/methods``); ``secondaries`` False: the primary only, the others left
    pending (the daemon runs them as jobs of their own).  The recording is read once and H(f)
    computed once (the expert estimator fits what ``processed/steps`` holds)."""
    rec = read_recording(path)
    response = checked_response(rec)
    process_recording(path, rec, response)
    if secondaries:
        return identify_all(path, rec, response)
    return identify_primary(path, rec, response)[1]


async def run_and_identify(cfg: StationConfig, request: RunRequest, out_dir: Path, *, sim: bool,
                           on_progress: Callable[[Progress], None] | None = None,
                           sim_clock: Clock | None = None) -> CalibrationResult:
    """Check the request (before anything moves), run it, then process and identify the recording.
    ``sim_clock``: the simulated rig in-process on this clock (see :func:`station.run.rig.connect`)."""
    plan = plan_run(cfg, request)
    async with connect(plan.config, sim=sim, first_radius_m=plan.steps[0].crank_radius_m,
                       sim_clock=sim_clock) as rig:
        proc = Procedure(plan, rig, out_dir, on_progress=on_progress)
        outcome = await proc.execute()
    if outcome.exit_status != "completed":
        return CalibrationResult(outcome, None)
    return CalibrationResult(outcome, process_and_identify(outcome.path))
