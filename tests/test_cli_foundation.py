"""The foundation's commands end to end: ``station simulate``, ``station export``, ``station import``.

A few tests run the installed console script in a subprocess (what an operator types); the others
call ``station.cli.main`` in-process.  Every command that writes a recording prints its path as the
last line of its output; refusals exit with 2 (bad input) or 1 and leave no file behind.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import station
from station.cli import main
from station.interchange import export_run
from station.recording import read_recording


def _station() -> list[str]:
    exe = shutil.which("station")
    return [exe] if exe else [sys.executable, "-m", "station.cli"]


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*_station(), *args], cwd=cwd, capture_output=True, text=True, timeout=120)


def _last_line(text: str) -> str:
    lines = text.strip().splitlines()
    assert lines, "no output"
    return lines[-1]


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")) if folder.exists() else []


def _write(path: Path, data: Any) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


# -- the console script ----------------------------------------------------------------------------

def test_console_script_version(tmp_path: Path) -> None:
    res = _run(["--version"], tmp_path)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == f"sinecal {station.__version__}"


@pytest.mark.slow
def test_station_simulate_prints_the_recording_path_last(tmp_path: Path, fast_config_file: Path) -> None:
    out = tmp_path / "recs"
    res = _run(["simulate", "--config", str(fast_config_file), "--out", str(out), "--seed", "5"], tmp_path)
    assert res.returncode == 0, res.stderr
    assert "Traceback" not in res.stderr
    path = Path(_last_line(res.stdout))
    assert path.parent == out and path.suffix == ".h5"
    assert _files(out) == [path.name]  # no *.partial left over
    rec = read_recording(path)
    assert rec.complete and rec.exit_status == "completed" and rec.source == "simulate"
    assert rec.documents[0]["plan"]["seed"] == 5
    assert [s.crank_frequency_hz for s in rec.steps] == [4.0, 30.0, 100.0]


@pytest.mark.slow
def test_station_export_then_import_round_trip(tmp_path: Path, sim_recording_one_radius: Path) -> None:
    res = _run(["export", str(sim_recording_one_radius), "--out", str(tmp_path / "x")], tmp_path)
    assert res.returncode == 0, res.stderr
    run_yaml = Path(_last_line(res.stdout))
    assert run_yaml.name == "RUN.yaml" and run_yaml.parent.parent == tmp_path / "x"

    res = _run(["import", str(run_yaml), "--out", str(tmp_path / "in")], tmp_path)
    assert res.returncode == 0, res.stderr
    path = Path(_last_line(res.stdout))
    assert _files(tmp_path / "in") == [path.name]
    original, imported = read_recording(sim_recording_one_radius), read_recording(path)
    assert imported.complete and imported.source == "import"
    for a, b in zip(original.steps, imported.steps, strict=True):
        assert (a.crank_frequency_hz, a.crank_radius_m) == (b.crank_frequency_hz, b.crank_radius_m)
        for x, y in zip(original.step_signals(a), imported.step_signals(b), strict=True):
            np.testing.assert_array_equal(y, x)


@pytest.mark.slow
def test_station_import_refusal(tmp_path: Path, sim_recording_one_radius: Path) -> None:
    run_yaml = export_run(sim_recording_one_radius, tmp_path / "x")
    csv = run_yaml.parent / "step01.csv"
    lines = csv.read_text(encoding="utf-8").splitlines()
    lines[41] = lines[41].rsplit(",", 1)[0] + ",0.5V"
    csv.write_text("\n".join(lines) + "\n", encoding="utf-8")
    out = tmp_path / "in"
    out.mkdir()
    res = _run(["import", str(run_yaml), "--out", str(out)], tmp_path)
    assert res.returncode == 2
    assert res.stdout == ""
    assert f"station import: error: {csv.resolve()}, line 42: column force_V: a number expected, got '0.5V'" in (
        res.stderr)
    assert "Traceback" not in res.stderr
    assert _files(out) == []


# -- in-process: simulate --------------------------------------------------------------------------

def test_simulate_defaults_to_the_configs_recordings_dir(tmp_path: Path, fast_config_dict: dict[str, Any],
                                                         monkeypatch: pytest.MonkeyPatch,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    fast_config_dict["station"]["recordings_dir"] = "data/runs"
    cfg = _write(tmp_path / "c.yaml", fast_config_dict)
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "--config", str(cfg)]) == 0
    path = Path(_last_line(capsys.readouterr().out))
    assert path.parent == Path("data/runs")
    assert (tmp_path / path).is_file()
    assert read_recording(tmp_path / path).documents[0]["plan"]["seed"] == 1  # the config's seed


@pytest.mark.parametrize(("edit", "fragment"), [
    (lambda d: d["rig"].update(top_mass_kg=-1), "rig.top_mass_kg = -1: Input should be greater than 0; "
                                               "allowed: value > 0 and <= 500"),
    (lambda d: d["plan"]["steps"][0].update(speed=3), "plan.steps.0.speed: unknown key (received 3)"),
    (lambda d: d["plan"]["steps"][2].update(crank_radius_m=0.001),
     "step 3 (100 Hz, 0.001 m): peak force 10635 N exceeds the limit 4000 N"),
    (lambda d: d["plan"]["steps"][0].update(crank_frequency_hz=0.5),
     "crank frequency 0.5 Hz is outside the rig's range [1, 100] Hz"),
    (lambda d: d.pop("simulation"), "the configuration has no 'simulation' section"),
])
def test_simulate_refuses_bad_configs_and_writes_nothing(tmp_path: Path, fast_config_dict: dict[str, Any],
                                                         capsys: pytest.CaptureFixture[str], edit: Any,
                                                         fragment: str) -> None:
    edit(fast_config_dict)
    cfg = _write(tmp_path / "bad.yaml", fast_config_dict)
    out = tmp_path / "out"
    assert main(["simulate", "--config", str(cfg), "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("station simulate: error: ")
    assert fragment in captured.err
    assert _files(out) == []


def test_simulate_missing_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", "--config", str(tmp_path / "none.yaml"), "--out", str(tmp_path / "o")]) == 2
    assert "cannot read configuration" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


# -- in-process: import / export -------------------------------------------------------------------

def test_import_defaults_to_recordings(tmp_path: Path, sim_recording_one_radius: Path,
                                       monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["export", str(sim_recording_one_radius)]) == 0
    run_yaml = Path(_last_line(capsys.readouterr().out))
    assert run_yaml.parent.parent == Path(".")
    assert main(["import", str(run_yaml)]) == 0
    path = Path(_last_line(capsys.readouterr().out))
    assert path.parent == Path("recordings") and (tmp_path / path).is_file()


def test_export_writes_several_radii(tmp_path: Path, sim_recording: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    """The station's default plan (a radius per step) exports as sinecal-csv v2."""
    assert main(["export", str(sim_recording), "--out", str(tmp_path)]) == 0
    run_yaml = Path(_last_line(capsys.readouterr().out))
    assert "format_version: 2" in run_yaml.read_text(encoding="utf-8")


def test_export_of_a_missing_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["export", str(tmp_path / "nope.h5"), "--out", str(tmp_path)]) == 2
    assert "no such recording" in capsys.readouterr().err


def test_import_of_a_missing_run_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["import", str(tmp_path / "RUN.yaml"), "--out", str(tmp_path / "o")]) == 2
    assert f"{tmp_path / 'RUN.yaml'}: cannot read: No such file or directory" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_a_failure_outside_the_station_is_one_clear_line_without_a_traceback(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """A driver's or the system's exception (not a StationError) ends the command with exit code 1 and
    one line naming it, the JSON refusal under --json; the traceback is logged only with -v."""
    import station.commands.calibrate as calibrate

    def fails(args: Any) -> int:
        raise TimeoutError("no reply to 'STAT?' (#2) within 1.0 s")

    monkeypatch.setattr(calibrate, "run", fails)
    assert main(["calibrate", "--sim", "--json"]) == 1
    out, err = capsys.readouterr()
    assert "station calibrate: error: TimeoutError: no reply to 'STAT?' (#2) within 1.0 s" in err
    assert "-v for the details" in err and "Traceback" not in err
    assert '"kind": "TimeoutError"' in out and '"exit_code": 1' in out
