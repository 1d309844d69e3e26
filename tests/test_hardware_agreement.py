"""The configuration agrees with the hardware it drives, or is refused before anything moves.

The crank ramp against the drive profile's ramp register(s), refused at plan time (``plan_run``, the
API's 422 at the configuration field, ``station calibrate`` in one line); the DAQ bridge's ``HW?``
against ``daq.adc_bits``, the channels, ``devices.daq_link`` and ``daq.sample_rate_hz``, refused at
connect.  Every refusal names the field, the value and the limit, and the drive stays untouched
(the emulator's register writes and commands are empty).  The limits come from the profiles
themselves, never from a number written here.
"""

from __future__ import annotations

import asyncio
import dataclasses
from pathlib import Path
from typing import Any

import h5py
import pytest
import yaml

import drivers.sim.rig as simrig
import station.run.rig as rigmod
from drivers.daq.bridge import parse_hardware
from drivers.motor import load_profile, shipped_profiles
from drivers.sim.clock import VirtualClock
from drivers.sim.rig import SimRig
from station.cli import main
from station.config import parse_config
from station.errors import HardwareMismatchError, LimitError
from station.run.hardware import check_daq_hardware
from station.run.request import default_request, plan_run
from station.run.rig import connect
from tests.conftest import fast_dict, station_config
from tests.station_support import (
    CAPPED,
    Daemon,
    app_in_process,
    daemon_config,
    run_body,
    wait_state,
)


def _ramp_case(profile: str, beyond: str) -> tuple[str, float, tuple[float, float]]:
    """The profile, a ramp just beyond its fastest (``max``) or slowest (``min``) one, its range."""
    dev = load_profile(profile).device
    lo, hi = dev.min_ramp_hz_per_s, dev.max_ramp_hz_per_s
    return profile, (hi * 1.5 if beyond == "max" else lo / 2), (lo, hi)


@pytest.mark.parametrize(("profile", "beyond"), [("sinecal-crank", "max"), ("automationdirect-gs2", "min"),
                                                 ("siemens-sinamics-v20", "min")])
def test_a_ramp_the_drive_profile_does_not_take_is_refused_at_plan_time(profile: str, beyond: str) -> None:
    name, acc, (lo, hi) = _ramp_case(profile, beyond)
    cfg = station_config(fast=True, acceleration_hz_per_s=acc, rig={"motor": {"profile": name}},
                         steps=((10.0, 0.001),))
    with pytest.raises(LimitError) as exc:
        plan_run(cfg, default_request(cfg))
    e = exc.value
    assert (e.field, e.value, e.limit, e.in_config) == ("rig.acceleration_hz_per_s", acc, (lo, hi), True)
    assert e.loc == ["config", "rig", "acceleration_hz_per_s"]
    assert f"rig.acceleration_hz_per_s {acc:g} Hz/s" in str(e) and repr(name) in str(e)
    assert f"{lo:.4g}..{hi:.4g} Hz/s" in str(e)


def test_the_shipped_crank_drive_refuses_ramps_above_100_hz_per_s() -> None:
    """The figure the drive's manual gives (docs/motor-registers.md), read back through the profile."""
    dev = load_profile("sinecal-crank").device
    assert (dev.min_ramp_hz_per_s, dev.max_ramp_hz_per_s) == (0.01, 100.0)
    for at_limit in (dev.min_ramp_hz_per_s, dev.max_ramp_hz_per_s):
        cfg = station_config(fast=True, acceleration_hz_per_s=at_limit)
        assert plan_run(cfg, default_request(cfg)).config.rig.acceleration_hz_per_s == at_limit


@pytest.mark.slow
def test_the_api_answers_422_at_the_configuration_field_and_writes_nothing_to_the_drive(tmp_path: Path) -> None:
    hi = load_profile("sinecal-crank").device.max_ramp_hz_per_s
    d = daemon_config(tmp_path)
    d["rig"]["acceleration_hz_per_s"] = hi + 50.0

    async def go() -> None:
        async with app_in_process(tmp_path, config=d, **CAPPED) as (manager, c):
            r = await c.post("/runs", json=run_body())
            assert r.status_code == 422, r.text
            (err,) = r.json()["errors"]
            assert err["loc"] == ["config", "rig", "acceleration_hz_per_s"] and err["input"] == hi + 50.0
            assert f"{hi + 50.0:g} Hz/s" in err["msg"] and f"..{hi:g} Hz/s" in err["msg"]
            assert "'sinecal-crank'" in err["msg"]
            rig = manager.link.rig
            assert rig is not None and rig.sim is not None
            assert not rig.sim.image.writes and not rig.sim.image.commands_seen  # nothing reached the drive
            assert not rig.sim.motor.snapshot().enabled
            drive = (await c.get("/station")).json()["limits"]["drive"]  # the limits the page can show
            assert drive == {"profile": "sinecal-crank", "crank_frequency_hz": {"min": 0.0, "max": 100.0},
                             "acceleration_hz_per_s": {"min": 0.01, "max": hi}}

    asyncio.run(go())


@pytest.mark.slow
def test_at_the_drives_fastest_ramp_a_run_goes_through_and_the_drive_takes_it(tmp_path: Path) -> None:
    hi = load_profile("sinecal-crank").device.max_ramp_hz_per_s
    d = daemon_config(tmp_path)
    d["rig"]["acceleration_hz_per_s"] = hi

    async def go() -> None:
        async with app_in_process(tmp_path, config=d, **CAPPED) as (manager, c):
            r = await c.post("/runs", json=run_body(freqs=(10.0,)))
            assert r.status_code == 202, r.text
            st = await wait_state(c, r.json()["id"])
            assert st["state"] in ("identifying", "completed"), st
            rig = manager.link.rig
            assert rig.sim.image.writes["acceleration_ramp"] >= 1 and "enable" in rig.sim.image.commands_seen
            rec = tmp_path / st["recording"]
            with h5py.File(rec, "r") as f:  # the bridge's own figures, and the LSB of its resolution
                raw = f["raw"].attrs
                assert int(raw["daq_adc_bits"]) == 16 and raw["daq_channels"] == "disp,force"
                lsb = 2.0 * d["daq"].get("force_range_V", 10.0) / 2 ** int(raw["daq_adc_bits"])
                assert f["raw/force"].attrs["volts_per_count"] == pytest.approx(lsb, rel=1e-12)

    asyncio.run(go())


def test_station_calibrate_says_it_in_one_line_and_moves_nothing(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    hi = load_profile("sinecal-crank").device.max_ramp_hz_per_s
    d = fast_dict(acceleration_hz_per_s=hi * 2, recordings_dir=tmp_path / "rec")
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(d))
    code = main(["calibrate", "--sim", "--config", str(cfg), "--steps", "10"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    (line,) = [ln for ln in err if "error" in ln]
    assert line.startswith("station calibrate: error: rig.acceleration_hz_per_s") and f"{hi * 2:g} Hz/s" in line
    assert not list((tmp_path / "rec").glob("*.h5*"))  # no run was started, no recording opened


# ------------------------------------------------------------------------------------------- the DAQ
class _Rigs:
    """The simulated rigs ``connect`` starts (their emulators are read after the refusal; ``connect``
    imports ``SimRig`` from ``drivers.sim.rig`` when it builds one)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, **override: Any) -> None:
        self.made: list[SimRig] = []
        made = self.made

        class Recorded(SimRig):
            def __init__(self, **kw: Any) -> None:
                super().__init__(**{**kw, **override})
                made.append(self)

        monkeypatch.setattr(simrig, "SimRig", Recorded)


def _connect_refused(cfg: Any) -> HardwareMismatchError:
    async def go() -> None:
        async with connect(cfg, sim=True, sim_clock=VirtualClock()):
            raise AssertionError("connected with a configuration the bridge disagrees with")

    with pytest.raises(HardwareMismatchError) as exc:
        asyncio.run(go())
    return exc.value


def test_adc_bits_that_disagree_with_the_bridge_are_refused_at_connect(monkeypatch: pytest.MonkeyPatch) -> None:
    """The simulated bridge quantises at (and reports) 16 bits; the configuration says 12."""
    real = rigmod.to_rig_physics

    def sixteen_bits(cfg: Any) -> Any:
        ph = real(cfg)
        return dataclasses.replace(ph, adc=dataclasses.replace(ph.adc, bits=16))

    monkeypatch.setattr(rigmod, "to_rig_physics", sixteen_bits)
    rigs = _Rigs(monkeypatch)
    e = _connect_refused(station_config(fast=True, daq={"adc_bits": 12}))
    assert (e.field, e.configured, e.reported, e.device) == ("daq.adc_bits", 12, 16, "daq")
    assert str(e).startswith("daq.adc_bits is 12 but the DAQ bridge reports bits=16")
    (rig,) = rigs.made
    assert not rig.image.writes and not rig.image.commands_seen and not rig.motor.snapshot().enabled


def test_the_daemon_with_such_a_configuration_runs_nothing_and_says_why(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """The daemon's rig stays unconnected: /health names the disagreement under the DAQ, a run is 503."""
    real = rigmod.to_rig_physics
    monkeypatch.setattr(rigmod, "to_rig_physics", lambda cfg: dataclasses.replace(
        real(cfg), adc=dataclasses.replace(real(cfg).adc, bits=16)))
    rigs = _Rigs(monkeypatch)
    d = daemon_config(tmp_path)
    d["daq"] = {**d.get("daq", {}), "adc_bits": 14}

    async def go() -> None:
        async with app_in_process(tmp_path, config=d) as (_, c):
            h = (await c.get("/health")).json()
            assert h["status"] == "degraded" and not h["rig"]["connected"]
            assert "daq.adc_bits is 14 but the DAQ bridge reports bits=16" in h["rig"]["daq"]["link_error"]
            assert h["rig"]["motor"]["link_error"] is None
            assert (await c.post("/runs", json=run_body())).status_code == 503

    asyncio.run(go())
    assert rigs.made and all(not r.image.writes and not r.image.commands_seen for r in rigs.made)


def test_a_link_kind_that_disagrees_with_the_bridge_is_refused_at_connect(monkeypatch: pytest.MonkeyPatch) -> None:
    rigs = _Rigs(monkeypatch, daq_link="usb-cdc")  # the bridge is on its USB port; the configuration says uart
    e = _connect_refused(station_config(fast=True))
    assert (e.field, e.configured, e.reported) == ("devices.daq_link", "uart", "usb-cdc")
    assert "link=usb-cdc" in str(e)
    (rig,) = rigs.made
    assert not rig.image.writes and not rig.image.commands_seen


@pytest.mark.parametrize(("hw", "field", "reported"), [
    ("bits=16 channels=force,temp clock_hz=1e6 rate_min=1000 rate_max=100000", "channels", "force,temp"),
    ("bits=16 channels=disp,force clock_hz=1e6 rate_min=1000 rate_max=10000", "daq.sample_rate_hz", (1000.0, 10000.0)),
    ("bits=12 channels=disp,force clock_hz=1e6 rate_min=1000 rate_max=100000", "daq.adc_bits", 12),
])
def test_each_disagreement_with_the_bridges_hw_reply_names_both_values(hw: str, field: str, reported: object) -> None:
    cfg = parse_config(fast_dict(), "test")
    assert cfg.daq.sample_rate_hz == 20_000.0 and cfg.daq.adc_bits == 16
    with pytest.raises(HardwareMismatchError) as exc:
        check_daq_hardware(cfg, parse_hardware("ACME,BRIDGE,1,1.0", f"OK HW adc=X {hw} link=uart"))
    assert exc.value.field == field and exc.value.reported == reported
    assert str(exc.value).startswith(f"{field} is ")
    # at the rate limit, and a 24-bit converter (the firmware's ADS131M02) whose frames carry 16-bit codes
    check_daq_hardware(cfg, parse_hardware("ACME,BRIDGE,1,1.0", "OK HW adc=ADS131M02 bits=24 channels=disp,force "
                                           "clock_hz=1e6 rate_min=1000 rate_max=20000 link=uart"))


def test_the_drive_profiles_documented_ranges_are_the_profiles_own() -> None:
    """docs/drive-profiles.md's table of set-point and ramp ranges, read back against each profile."""
    text = (Path(__file__).resolve().parent.parent / "docs" / "drive-profiles.md").read_text(encoding="utf-8")
    profiles = shipped_profiles()
    rows = {m[0]: m[1:] for m in (
        [c.strip().strip("`") for c in ln.strip("|").split("|")] for ln in text.splitlines()
        if ln.startswith("| `") and ln.rstrip().endswith("Hz/s |"))}
    assert sorted(rows) == sorted(profiles)
    for name, (setpoint, ramps) in rows.items():
        dev = load_profile(name).device
        assert setpoint == f"{dev.min_frequency_hz:g}..{dev.max_frequency_hz:g} Hz", name
        assert ramps == f"{dev.min_ramp_hz_per_s:.4g}..{dev.max_ramp_hz_per_s:.4g} Hz/s", name


@pytest.mark.slow
def test_station_serve_says_it_once_in_its_log_and_refuses_every_run(tmp_path: Path) -> None:
    """A real ``station serve --sim`` with a ramp its drive does not take: one log line at start, the
    page and API serve, each run is 422 at the configuration field, the drive is never enabled."""
    hi = load_profile("sinecal-crank").device.max_ramp_hz_per_s
    d = daemon_config(tmp_path / "recordings")
    d["rig"]["acceleration_hz_per_s"] = hi * 1.2
    with Daemon(tmp_path, workers=0, config=d) as daemon:
        r = daemon.c().post("/runs", json=run_body())
        assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["config", "rig", "acceleration_hz_per_s"]
        assert daemon.c().get("/health").json()["rig"]["connected"]
        lines = [ln for ln in daemon.log().splitlines() if "every run will be refused" in ln]
        assert len(lines) == 1 and f"rig.acceleration_hz_per_s {hi * 1.2:g} Hz/s" in lines[0], daemon.log()[-2000:]
        assert "'sinecal-crank'" in lines[0]
