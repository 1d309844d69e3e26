"""Calibration runs against the emulators, through the real drivers: every fault ends with the motor
stopped, a clear reason in the stop record and the samples kept.

The procedure's logic runs on the in-process simulated rig on a virtual clock (a run's seconds take
milliseconds); one complete run goes over the wire (Modbus TCP, pseudo-terminal) in real time, and
the killed process and the full disk are separate processes in real time."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from drivers.motor.controller import MotorController
from drivers.motor.transport import ModbusTransport
from drivers.sim import SimRigProcess
from drivers.sim.clock import VirtualClock
from station.config import load_config, parse_config
from station.recording import read_recording
from station.run.procedure import Procedure
from station.run.rig import ConnectedRig
from tests.disk_support import mounted_tmpfs
from tests.run_support import run_with, small_config


def recording_after(outcome: object) -> object:
    rec = read_recording(outcome.path)  # type: ignore[attr-defined]
    assert rec.displacement_m.size > 0
    return rec


@pytest.mark.parametrize("wire", [False, pytest.param(True, marks=(pytest.mark.slow, pytest.mark.waits))],
                         ids=["virtual", "wire"])  # over the wire: about 7 s of wall time, 1 s of CPU
@pytest.mark.slow
def test_completed_run_records_every_step(tmp_path: Path, wire: bool) -> None:
    outcome, _, motor = run_with(tmp_path, None, lambda r, p: None, wire=wire)
    assert outcome.exit_status == "completed", outcome.reason
    assert motor["speed_hz"] == 0.0 and not motor["enabled"]
    rec = recording_after(outcome)
    assert rec.complete and len(rec.steps) == 3 and rec.lost_samples.size == 0
    kinds = [d["kind"] for d in rec.documents]
    assert kinds[0] == "start" and kinds[-1] == "stop" and kinds.count("step") == 3
    stop = rec.documents[-1]
    assert stop["exit_status"] == "completed"
    step_doc = [d for d in rec.documents if d["kind"] == "step"][1]
    assert step_doc["units"]["crank_frequency_hz"] == "Hz" and "crank_angle_rad_at_start" in step_doc
    with h5py.File(outcome.path, "r") as f:  # the bridge as it reported itself at connect
        attrs = f["raw"].attrs
        assert (attrs["daq_adc"], attrs["daq_link"], attrs["daq_channels"]) == ("EMULATED", "uart", "disp,force")
        assert attrs["sample_rate_requested_hz"] == attrs["sample_rate_hz"] == 20_000.0
    for st in rec.steps:  # each window holds a steady sine at the step's frequency
        d, _ = rec.step_signals(st)
        spec = np.abs(np.fft.rfft(d - d.mean()))
        f_peak = np.argmax(spec) * 20_000 / d.size
        assert f_peak == pytest.approx(st.crank_frequency_hz, abs=1.0)


def test_abort_ramps_down_and_keeps_the_samples(tmp_path: Path) -> None:
    outcome, _, motor = run_with(tmp_path, lambda p: p.step == 1 and p.step_state == "recording",
                                 lambda rig, proc: proc.abort("technician pressed abort"))
    assert outcome.exit_status == "aborted" and "technician pressed abort" in outcome.reason
    assert motor["speed_hz"] == 0.0
    rec = recording_after(outcome)
    assert rec.exit_status == "aborted" and len(rec.steps) == 1
    assert rec.documents[-1]["reason"] == "technician pressed abort"


def test_motor_fault_stops_the_run(tmp_path: Path) -> None:
    outcome, _, motor = run_with(tmp_path, lambda p: p.step == 1 and p.step_state == "settling",
                                 lambda rig, proc: rig.sim.motor.inject_fault(3))
    assert outcome.exit_status == "failed"
    assert "motor fault 3 (overcurrent)" in outcome.reason
    assert motor["speed_hz"] == 0.0
    assert recording_after(outcome).exit_status == "failed"


def test_a_run_and_its_stop_never_hold_the_virtual_clock(tmp_path: Path) -> None:
    """Every wait of the procedure, the stop's read-back and the shutdown steps included, is one the
    clock sees: no task holds it while it waits on another one.  With a hold of 30 s a stall would
    be released (counted) only after 30 s of real time; none is."""
    clock = VirtualClock(hold_s=30.0)
    procs: list[Procedure] = []

    def fault(rig: ConnectedRig, proc: Procedure) -> None:
        procs.append(proc)
        rig.sim.motor.inject_fault(3)
    outcome, _, motor = run_with(tmp_path, lambda p: p.step == 1 and p.step_state == "settling", fault,
                                 clock=clock)
    assert outcome.exit_status == "failed" and motor["speed_hz"] == 0.0
    # the drive was read back to standstill (a stalled clock lets the read-back's time-out run out first)
    check = procs[0].drive_check
    assert check is not None and check.standstill is True, check
    assert clock.released == 0


def test_emergency_stop_mid_step_is_an_abort_and_the_crank_stops(tmp_path: Path) -> None:
    def estop(rig: ConnectedRig, proc: Procedure) -> None:
        proc.abort("emergency stop")
        rig.sim.motor.emergency_stop()
    outcome, _, motor = run_with(tmp_path, lambda p: p.step == 1 and p.step_state == "settling", estop)
    assert outcome.exit_status == "aborted" and outcome.reason == "emergency stop"
    assert motor["speed_hz"] == 0.0 and not motor["enabled"]
    rec = recording_after(outcome)
    assert rec.exit_status == "aborted" and len(rec.steps) == 1


def test_lost_motor_link_fails_the_run_and_the_controllers_watchdog_stops_the_crank(tmp_path: Path) -> None:
    outcome, rig, motor = run_with(tmp_path, lambda p: p.step == 1 and p.step_state == "recording",
                                   lambda rig, proc: rig.motor.transport.cut())
    assert outcome.exit_status == "failed" and "MotorLinkError" in outcome.reason
    assert motor["speed_hz"] == 0.0  # nobody could stop it over the link: the watchdog did
    assert rig.sim.motor.snapshot().fault_code == 1  # watchdog_expired
    assert recording_after(outcome).exit_status == "failed"


def test_stalled_daq_stops_the_run(tmp_path: Path) -> None:
    outcome, _, motor = run_with(tmp_path, lambda p: p.step == 0 and p.step_state == "recording",
                                 lambda rig, proc: rig.sim.daq.stall(4.0))
    assert outcome.exit_status == "failed" and "stalled" in outcome.reason
    assert motor["speed_hz"] == 0.0
    rec = recording_after(outcome)
    assert rec.displacement_m.size > 0.2 * 20_000


def test_crc_storm_stops_the_run_and_keeps_every_valid_sample(tmp_path: Path) -> None:
    first_bad: list[int] = []

    def storm(rig: ConnectedRig, proc: Procedure) -> None:
        seq = proc.acq.samples // 256 + 4 if proc.acq else 0
        first_bad.append(seq * 256)
        rig.sim.daq.corrupt_frames(range(seq, seq + 2000))
    outcome, _, motor = run_with(tmp_path, lambda p: p.step == 0 and p.step_state == "recording", storm)
    assert outcome.exit_status == "failed" and "corrupted" in outcome.reason and "frames rejected" in outcome.reason
    assert motor["speed_hz"] == 0.0
    rec = recording_after(outcome)
    # no sample of a corrupted frame was stored; every valid one before the storm was
    assert rec.displacement_m.size == first_bad[0]
    assert rec.lost_samples.size == 0


def test_lost_daq_link_stops_the_run(tmp_path: Path) -> None:
    outcome, _, motor = run_with(tmp_path, lambda p: p.step == 1 and p.step_state == "recording",
                                 lambda rig, proc: rig.sim.daq.close_port())
    assert outcome.exit_status == "failed"
    assert motor["speed_hz"] == 0.0
    rec = recording_after(outcome)
    assert len(rec.steps) == 1  # the first step was recorded before the link went


@pytest.mark.slow
def test_a_few_lost_frames_mark_the_step(tmp_path: Path) -> None:
    seqs: list[int] = []

    def drop(rig: ConnectedRig, proc: Procedure) -> None:
        seq = proc.acq.samples // 256 if proc.acq else 0
        seqs.extend([seq + 5, seq + 6, seq + 9])
        rig.sim.daq.drop_frames(seqs)
    outcome, _, _ = run_with(tmp_path, lambda p: p.step == 1 and p.step_state == "recording", drop)
    assert outcome.exit_status == "completed", outcome.reason
    rec = recording_after(outcome)
    # exactly the dropped frames, at their sample positions: frames 5-6 together, 9 alone
    assert rec.lost_samples.tolist() == [[seqs[0] * 256, 512], [seqs[2] * 256, 256]]
    marked = [s for s in rec.steps if not s.usable]
    assert [s.index for s in marked] == [1] and marked[0].lost_in_window == 768


# ---- the acquiring process killed, and the disk full: separate processes ------------------------

def _external_config(tmp_path: Path, addresses: object, radius: float) -> Path:
    d = small_config(steps=[(f, radius) for f in (10.0, 20.0, 30.0)],
                     record_s=3.0)
    d["devices"] = {"motor_url": f"modbus-tcp://{addresses.modbus_tcp[0]}:{addresses.modbus_tcp[1]}",
                    "daq_port": addresses.daq, "crank_radius_m": radius}
    p = tmp_path / "station.yaml"
    p.write_text(yaml.safe_dump(d))
    load_config(p)
    return p


async def _motor_state(addresses: object) -> tuple[float, int]:
    m = MotorController()
    await m.connect(ModbusTransport.tcp(*addresses.modbus_tcp))
    st = await m.read_status()
    await m.close()
    return st.actual_speed_hz, st.fault_code


@pytest.mark.slow
@pytest.mark.waits  # a run over the wire, killed, and the drive's watchdog: about 7 s
def test_kill_9_leaves_a_readable_interrupted_file_and_the_watchdog_stops_the_motor(tmp_path: Path) -> None:
    with SimRigProcess(seed=3) as sim:
        cfg = _external_config(tmp_path, sim.addresses, 0.002)
        out = tmp_path / "rec"
        log = (tmp_path / "calibrate.log").open("wb")
        proc = subprocess.Popen([sys.executable, "-m", "station.cli", "calibrate", "--config", str(cfg),
                                 "--out", str(out)], stdout=log, stderr=log)
        # wait until the run is recording with the crank turning, then a little longer
        deadline = time.monotonic() + 60
        speed_before = 0.0
        while time.monotonic() < deadline and proc.poll() is None:
            if list(out.glob("*.partial")):
                speed_before, _ = asyncio.run(_motor_state(sim.addresses))
                if speed_before > 1.0:
                    break
            time.sleep(0.1)
        assert proc.poll() is None, (tmp_path / "calibrate.log").read_text()[-2000:]
        time.sleep(1.5)
        t_kill = time.time()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        log.close()
        assert speed_before > 1.0  # the crank was turning when the process died
        # a lost link stops the motor: the controller's watchdog expires (1 s) and it ramps down
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            speed, fault = asyncio.run(_motor_state(sim.addresses))
            if speed == 0.0:
                break
            time.sleep(0.2)
        assert speed == 0.0 and fault == 1  # watchdog_expired
    partial = list(out.glob("*.h5.partial"))
    assert len(partial) == 1
    rec = read_recording(partial[0])
    assert not rec.complete and rec.exit_status == "interrupted"
    start = json.loads(json.dumps(rec.documents[0]))
    assert start["kind"] == "start"
    from datetime import datetime
    t_start = datetime.fromisoformat(rec.start_time).timestamp()
    # everything up to the last flush is there: at most 1 s (plus the stream's start-up) is missing
    assert rec.displacement_m.size >= (t_kill - t_start - 1.3) * 20_000
    assert rec.displacement_m.size <= (t_kill - t_start) * 20_000


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A real 3 MiB file system (tmpfs); needs root, as CI has."""
    with mounted_tmpfs(tmp_path, 3) as mnt:
        yield mnt


@pytest.mark.slow
def test_full_disk_fails_the_run_keeps_the_samples_and_stops_the_motor(tmp_path: Path, small_disk: Path) -> None:
    d = small_config(record_s=3.0)
    d["station"]["min_free_mb"] = 2.5  # 3 MiB disk, 2.5 MiB reserve: about 0.5 MiB of room
    outcome, _, motor = run_with(small_disk, None, lambda r, p: None, cfg=parse_config(d, "small-disk"))
    assert outcome.exit_status == "failed" and "disk nearly full" in outcome.reason
    assert motor["speed_hz"] == 0.0
    files = list(small_disk.glob("*.h5*"))
    assert len(files) == 1 and files[0].suffix == ".h5"  # closed properly, not left partial
    rec = read_recording(files[0])
    assert rec.complete and rec.exit_status == "failed" and "disk nearly full" in rec.reason
    assert rec.displacement_m.size > 20_000  # what was written before the reserve was reached is there
