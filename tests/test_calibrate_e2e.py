"""End to end: a calibration over 4 steps through emulators, real drivers, HDF5, processing and
identification; k_f and b_f must match the simulation's truth.

Once in-process on the virtual clock (the run's logic, in about a second), once as an operator
types it, ``station calibrate --sim`` in a subprocess over Modbus TCP and a pty in real time."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import h5py
import pytest
import yaml

from drivers.sim.clock import VirtualClock
from station.cli import main
from station.config import parse_config
from station.recording import read_recording, read_result, read_stored
from station.run.calibrate import run_and_identify
from station.run.request import default_request
from tests.conftest import station_dict

STEPS = [8.0, 30.0, 60.0, 95.0]


def _config() -> dict[str, Any]:
    """Short steps; the expert estimator alone (the one these tests check against the truth; the
    paper's swarm methods listed beside it are the daemon's and the batch's tests' business)."""
    return station_dict(settle_s=0.3, record_s=1.5, acceleration_hz_per_s=50.0,
                        identification={"methods": [{"method": "fd", "model": "auto"}]})


def _check_against_the_truth(out: dict[str, Any], truth: dict[str, float]) -> None:
    assert out["exit_status"] == "completed" and out["lost_samples"] == 0, out.get("reason")
    k_f, b_f = out["parameters"]["k_f"], out["parameters"]["b_f"]
    assert k_f["unit"] == "N/m" and b_f["unit"].replace("·", "*") == "N*s/m"
    assert k_f["identifiable"] and b_f["identifiable"]
    assert abs(k_f["value"] / truth["k_f"] - 1) < 1e-3
    assert abs(b_f["value"] / truth["b_f"] - 1) < 0.02
    # the stated uncertainties are consistent with the actual errors (within 4 sigma)
    assert abs(k_f["value"] - truth["k_f"]) < 4 * k_f["std"]
    assert abs(b_f["value"] - truth["b_f"]) < 4 * b_f["std"]

    rec = read_recording(out["recording"])
    assert rec.complete and rec.exit_status == "completed" and len(rec.steps) == 4
    assert [s.crank_frequency_hz for s in rec.steps] == STEPS
    assert read_result(out["recording"], "steps", group="processed") is not None
    assert any(k.startswith("identify_") for k in read_stored(out["recording"]))
    with h5py.File(out["recording"], "r") as f:
        assert "results" not in f or not len(f["results"])  # beside the recording, never inside
        assert f["raw/force"].attrs["physical_unit"] == "V" and f["raw/displacement"].attrs["physical_unit"] == "m"
        assert f.attrs["software_version"]


@pytest.mark.slow
def test_calibration_on_the_virtual_clock_identifies_the_truth(tmp_path: Path) -> None:
    d = _config()
    cfg = parse_config(d, "e2e")
    clock = VirtualClock()
    t0 = clock.monotonic()
    result = asyncio.run(run_and_identify(cfg, default_request(cfg, STEPS), tmp_path / "rec", sim=True,
                                          sim_clock=clock))
    _check_against_the_truth(json.loads(json.dumps(result.to_json())), d["simulation"]["truth"])
    assert clock.monotonic() - t0 > 4 * (0.3 + 1.5)  # the run's time passed on the rig's clock


@pytest.mark.slow
@pytest.mark.waits  # a run over the wire in real time: about 10 s
def test_station_calibrate_sim_over_the_wire(tmp_path: Path) -> None:
    """What an operator types, in real time over Modbus TCP and a pty: two steps, every stage
    (the identification against the truth is the in-process test's job, on the same code)."""
    d = _config()
    d["plan"].update({"record_s": 1.0})
    d["rig"]["acceleration_hz_per_s"] = 100.0  # the drive's fastest ramp: the ramps are not what this is about
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(d))
    res = subprocess.run([sys.executable, "-m", "station.cli", "calibrate", "--sim", "--config", str(cfg),
                          "--steps", "8,60", "--out", str(tmp_path / "rec"), "--json"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout)
    assert out["exit_status"] == "completed" and out["lost_samples"] == 0, out.get("reason")
    truth = d["simulation"]["truth"]
    k_f = out["parameters"]["k_f"]
    assert k_f["unit"] == "N/m" and abs(k_f["value"] - truth["k_f"]) < 4 * k_f["std"]
    rec = read_recording(out["recording"])
    assert rec.complete and [s.crank_frequency_hz for s in rec.steps] == [8.0, 60.0]
    assert read_result(out["recording"], "steps", group="processed") is not None
    assert any(k.startswith("identify_") for k in read_stored(out["recording"]))


def test_unsafe_steps_are_refused_before_anything_moves(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", "--sim", "--steps", "150", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "150 Hz" in err and "range" in err
    assert not any(tmp_path.iterdir())  # no recording: the run never started


@pytest.mark.parametrize("bad", ["3,x", ","])
def test_bad_step_list_is_a_clear_error(bad: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", "--sim", "--steps", bad, "--out", str(tmp_path)]) == 2
    assert "--steps" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
