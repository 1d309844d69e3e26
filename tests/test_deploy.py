"""deploy/: the systemd units are accepted by ``systemd-analyze verify`` (when it is installed), their
ExecStart lines are command lines that ``station`` parses, and the settings the brief asks for are there."""

from __future__ import annotations

import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

from station.cli import build_parser

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
UNITS = ("sinecal.service", "sinecal-batch.service", "sinecal-batch.timer")
VENV_STATION = "/opt/sinecal/venv/bin/station"


def _unit(name: str) -> dict[str, dict[str, list[str]]]:
    """Sections -> key -> values (systemd allows repeated keys)."""
    out: dict[str, dict[str, list[str]]] = {}
    sec = None
    for raw in (DEPLOY / name).read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            sec = out.setdefault(line[1:-1], {})
            continue
        assert sec is not None and "=" in line, f"{name}: unexpected line {raw!r}"
        key, value = line.split("=", 1)
        sec.setdefault(key.strip(), []).append(value.strip())
    return out


@pytest.mark.parametrize(("unit", "command"), [("sinecal.service", "serve"), ("sinecal-batch.service", "batch")])
def test_exec_start_is_a_station_command_line(unit: str, command: str) -> None:
    [line] = _unit(unit)["Service"]["ExecStart"]
    argv = shlex.split(line)
    assert argv[0] == VENV_STATION
    args = build_parser().parse_args(argv[1:])  # SystemExit on an unknown command or option
    assert args.command == command
    assert args.config == Path("/etc/sinecal/station.yaml")


def test_units_have_the_required_settings() -> None:
    daemon, batch, timer = (_unit(u) for u in UNITS)
    d = daemon["Service"]
    assert d["Restart"] == ["on-failure"] and d["User"] == ["sinecal"] and d["Group"] == ["sinecal"]
    for key, value in (("NoNewPrivileges", "yes"), ("ProtectSystem", "strict"), ("ProtectHome", "yes"),
                       ("PrivateTmp", "yes"), ("CapabilityBoundingSet", "")):
        assert d[key] == [value], key
        assert batch["Service"][key] == [value], key
    assert daemon["Install"]["WantedBy"] == ["multi-user.target"]
    assert batch["Service"]["Type"] == ["oneshot"] and batch["Service"]["User"] == ["sinecal"]
    t = timer["Timer"]
    assert t["Persistent"] == ["true"] and t["OnCalendar"] == ["*-*-* 02:30:00"]
    assert t["Unit"] == ["sinecal-batch.service"] and (DEPLOY / t["Unit"][0]).is_file()
    assert timer["Install"]["WantedBy"] == ["timers.target"]


def test_systemd_analyze_verify_accepts_the_units(tmp_path: Path) -> None:
    analyze, station = shutil.which("systemd-analyze"), shutil.which("station")
    if analyze is None or station is None:
        pytest.skip("systemd-analyze or the installed station script not available")
    # verify checks that ExecStart's program exists: point it at this machine's station script
    for u in UNITS:
        (tmp_path / u).write_text((DEPLOY / u).read_text(encoding="utf-8").replace(VENV_STATION, station),
                                  encoding="utf-8")
    res = subprocess.run([analyze, "verify", *(str(tmp_path / u) for u in UNITS)], capture_output=True, text=True,
                         timeout=60, cwd=tmp_path)
    # it exits 0 on some problems (an unparsable value is "ignored" with a warning): no output at all
    mentions = [ln for ln in (res.stdout + res.stderr).splitlines() if any(u in ln for u in UNITS)]
    assert res.returncode == 0 and not mentions, res.stdout + res.stderr
