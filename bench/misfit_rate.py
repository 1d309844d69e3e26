"""False-alarm rate of the model-misfit test on an ideal rig (no effects); prints JSON.

The expert estimator flags ``model_misfit`` when chi^2/dof of its weighted fit exceeds
1 + 3 sqrt(2/dof) (``station/ident/response/frf.py``).  On ideal data the flag is a false alarm; its
nominal rate is the chi^2 tail beyond that threshold.  Measured here on runs of the configured plan
(config/sim-5kN.yaml, 5 steps, effects off), each with its own seed:

- ``offline``: recordings written straight from the physics (``station.simulate``);
- ``rig``: the simulated rig in-process on a virtual clock, through the real drivers (Modbus image,
  the DAQ bridge's byte stream from its emulator) and the run procedure, as the daemon runs it.

Usage: python bench/misfit_rate.py [--offline N] [--rig M]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.stats import chi2 as chi2_dist
from scipy.stats import kstest

from drivers.sim.clock import VirtualClock
from station.config import StationConfig, load_config
from station.ident.identify import identify_recording
from station.ident.result import IdentificationResult
from station.recording import read_recording
from station.run.calibrate import run_and_identify
from station.run.request import RunRequest, StepSpec
from station.simulate import simulate_run

ROOT = Path(__file__).resolve().parents[1]


def _with_seed(cfg: StationConfig, seed: int) -> StationConfig:
    assert cfg.simulation is not None
    return cfg.model_copy(update={"simulation": cfg.simulation.model_copy(update={"seed": seed})})


def _row(res: IdentificationResult) -> dict[str, float | bool]:
    return {"chi2_per_dof": float(res.fit.chi2_per_dof), "dof": float(res.extra["dof"]),
            "misfit": any(c.name == "model_misfit" for c in res.checks)}


def offline(cfg: StationConfig, n: int, tmp: Path) -> list[dict[str, float | bool]]:
    rows = []
    for seed in range(n):
        path = simulate_run(cfg, tmp / f"offline{seed}", seed=1000 + seed)
        rows.append(_row(identify_recording(read_recording(path), "fd")))
    return rows


def rig(cfg: StationConfig, n: int, tmp: Path) -> list[dict[str, float | bool]]:
    rows = []
    for seed in range(n):
        c = _with_seed(cfg, 2000 + seed)
        req = RunRequest(transducer_id=c.transducer.id, top_mass_kg=c.rig.top_mass_kg,
                         steps=[StepSpec(**s.model_dump(exclude_none=True)) for s in c.plan.steps],
                         methods=[{"method": "fd", "model": "auto"}])  # type: ignore[list-item]
        res = asyncio.run(run_and_identify(c, req, tmp / f"rig{seed}", sim=True, sim_clock=VirtualClock()))
        if res.identification is None:
            raise RuntimeError(f"rig run {seed} did not complete: {res.outcome.reason}")
        rows.append(_row(res.identification))
    return rows


def summary(rows: list[dict[str, float | bool]]) -> dict[str, object]:
    if not rows:
        return {"runs": 0}
    dof = float(rows[0]["dof"])
    x = np.array([float(r["chi2_per_dof"]) for r in rows])
    flagged = sum(bool(r["misfit"]) for r in rows)
    return {"runs": len(rows), "dof": dof, "flagged": flagged, "rate": flagged / len(rows),
            "chi2_per_dof_median": float(np.median(x)), "chi2_per_dof_max": float(x.max()),
            "chi2_per_dof_mean": float(x.mean()), "expected_mean": 1.0,
            "expected_mean_std": math.sqrt(2 / dof / len(rows)),
            # do the chi2 values follow chi2(dof)/dof, as they should on ideal data?
            "ks_pvalue_chi2": float(kstest(x * dof, chi2_dist(dof).cdf).pvalue)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--offline", type=int, default=40, help="offline runs")
    ap.add_argument("--rig", type=int, default=10, help="runs through the in-process simulated rig")
    args = ap.parse_args()
    cfg = load_config(ROOT / "config" / "sim-5kN.yaml")
    out: dict[str, object] = {}
    with tempfile.TemporaryDirectory() as d:
        t = time.perf_counter()
        off = offline(cfg, args.offline, Path(d))
        out["offline"] = {**summary(off), "wall_s": round(time.perf_counter() - t, 1)}
        t = time.perf_counter()
        on = rig(cfg, args.rig, Path(d))
        out["rig_inprocess"] = {**summary(on), "wall_s": round(time.perf_counter() - t, 1)}
    dof = float((off or on)[0]["dof"]) if off or on else math.nan
    threshold = 1 + 3 * math.sqrt(2 / dof)
    out["threshold_chi2_per_dof"] = threshold
    out["nominal_false_alarm_rate"] = float(chi2_dist.sf(dof * threshold, dof))
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
