"""The simulated rig as a whole: both emulators share one motor; in-process, subprocess and CLI."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.daq import DaqBridge, SampleBlock, SerialLink
from drivers.motor import LinkPolicy, ModbusTransport, MotorController
from drivers.sim import SimRig, SimRigProcess
from drivers.sim.__main__ import HARDWARE_NICE


def samples(daq: DaqBridge, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    disp, force = [], []
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        ev = daq.get_event(0.2)
        if isinstance(ev, SampleBlock):
            disp.append(ev.displacement)
            force.append(ev.force)
    return np.concatenate(disp).astype(float), np.concatenate(force).astype(float)


def dominant_hz(x: np.ndarray, rate: float) -> float:
    spec = np.abs(np.fft.rfft((x - x.mean()) * np.hanning(len(x))))
    return float(np.fft.rfftfreq(len(x), 1 / rate)[np.argmax(spec)])


@pytest.mark.slow
def test_both_channels_move_with_the_emulated_motor() -> None:
    with SimRig(seed=5, crank_radius_m=0.01) as rig:
        daq = DaqBridge()
        daq.connect(SerialLink(rig.addresses.daq))
        daq.configure(rate_hz=20_000)
        daq.start()
        d0, f0 = samples(daq, 0.5)
        assert np.ptp(d0) < 200 and np.ptp(f0) < 200  # standstill: noise only

        async def spin_up() -> None:
            motor = MotorController()
            await motor.connect(ModbusTransport.tcp(*rig.addresses.modbus_tcp, policy=LinkPolicy()))
            await motor.set_watchdog_timeout(60.0)  # 0 (off) is refused with the drive enabled
            await motor.set_ramp(50.0)
            await motor.enable()
            await motor.set_frequency(12.0)
            await motor.wait_for_speed(12.0, timeout_s=3.0)
            await motor.close()  # no refresh needed for 60 s: the crank keeps turning

        asyncio.run(spin_up())
        d1, f1 = samples(daq, 1.0)
        daq.stop()
        daq.close()
    assert dominant_hz(d1, 20_000) == pytest.approx(12.0, abs=1.0)
    assert dominant_hz(f1, 20_000) == pytest.approx(12.0, abs=1.0)
    # 10 mm crank at 500 V/m: +-5 V on +-10 V, 16 bit: about +-16384 codes
    assert np.ptp(d1) == pytest.approx(2 * 16384, rel=0.03)
    # m_total * (2 pi f)^2 r * S * gain: ~26.3 kg * 56.8 m/s^2 * 2e-6 V/N * 1000 = 3.0 V = ~9800 codes
    assert 0.8 * 2 * 9800 < np.ptp(f1) < 1.2 * 2 * 9800
    # the force (spring, -m a) is in phase with the displacement: sin vs -(-w^2 sin)
    assert np.corrcoef(d1, f1)[0, 1] > 0.95


@pytest.mark.slow
def test_inprocess_daq_backend_streams_without_loss() -> None:
    with SimRig(seed=6, rtu=False) as rig:
        emu, link = rig.inprocess_daq()
        daq = DaqBridge()
        daq.connect(link)
        daq.configure(rate_hz=50_000, frame_samples=500)
        daq.start()
        time.sleep(0.5)
        summary = daq.stop()
        got = sum(ev.count for ev in daq.events(0.3) if isinstance(ev, SampleBlock))
        daq.close()
        emu.close()
    assert got == summary.samples_sent > 0.4 * 50_000
    assert summary.stats.samples_lost == 0


@pytest.mark.slow
def test_subprocess_rig_serves_both_devices(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")  # numpy's import starts threads before the emulators' code runs
    with SimRigProcess(seed=2) as proc:
        async def read_max() -> float:
            motor = MotorController()
            await motor.connect(ModbusTransport.tcp(*proc.addresses.modbus_tcp))
            value = await motor.read("max_frequency")
            await motor.close()
            return value

        assert asyncio.run(read_max()) == pytest.approx(100.0)
        daq = DaqBridge()
        daq.connect(SerialLink(proc.addresses.daq))
        assert daq.identify().startswith("SINECAL,DAQ-BRIDGE-EMU")
        daq.close()
        # hardware of its own: every thread of the emulators at the raised priority, where the OS gives it
        nices = {os.getpriority(os.PRIO_PROCESS, int(tid)) for tid in os.listdir(f"/proc/{proc.pid}/task")}
        assert nices == ({HARDWARE_NICE} if _may_raise_priority() else {os.nice(0)}), nices


def _may_raise_priority() -> bool:
    """Whether this process may lower a nice value (root or CAP_SYS_NICE): tried on a thread of its own."""
    got: list[bool] = []

    def attempt() -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, os.getpriority(os.PRIO_PROCESS, 0) - 1)
            got.append(True)
        except OSError:
            got.append(False)
    t = threading.Thread(target=attempt)
    t.start()
    t.join()
    return got[0]


@pytest.mark.slow
def test_station_sim_rig_prints_where_it_listens_and_stops_on_ctrl_c(tmp_path: Path) -> None:
    # its log goes to a file (a pipe nobody reads could fill and block it); a hang dumps its threads there.
    # Ctrl-C as from a terminal: a suite started in the background (``cmd &``) runs with SIGINT ignored,
    # which a child inherits and Python then keeps
    with open(tmp_path / "stderr.txt", "w+") as err:
        proc = subprocess.Popen([sys.executable, "-X", "faulthandler", "-m", "station.cli", "sim-rig", "--seed", "3"],
                                stdout=subprocess.PIPE, stderr=err, text=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        try:
            assert proc.stdout is not None
            lines = [proc.stdout.readline() for _ in range(3)]
            tcp = re.search(r"Modbus TCP\s+modbus-tcp://127\.0\.0\.1:(\d+)", lines[0])
            rtu = re.search(r"Modbus RTU\s+(/dev/pts/\d+)", lines[1])
            daq_path = re.search(r"serial\s+(/dev/pts/\d+)", lines[2])
            assert tcp and rtu and daq_path, lines
            daq = DaqBridge()
            daq.connect(SerialLink(daq_path.group(1)))
            assert daq.status()["state"] == "idle"
            daq.close()
            proc.send_signal(signal.SIGINT)
            try:
                code = proc.wait(timeout=30)  # a hang's bound (it ends in about 1 s; longer on a starved host)
            except subprocess.TimeoutExpired:
                proc.send_signal(signal.SIGABRT)  # faulthandler: every thread's stack into the log
                proc.wait(10)
                err.seek(0)
                pytest.fail(f"sim-rig did not end within 30 s of Ctrl-C; its log:\n{err.read()[-8000:]}")
            assert code == 130
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


@pytest.mark.slow
def test_crank_radius_changes_only_at_standstill() -> None:
    with SimRig(seed=7, rtu=False, crank_radius_m=0.01) as rig:
        rig.set_crank_radius(0.005)
        daq = DaqBridge()
        daq.connect(SerialLink(rig.addresses.daq))
        rig.motor.set_watchdog_timeout(60.0)  # 0 (off) is refused with the drive enabled
        rig.motor.set_ramp(100.0)
        rig.motor.set_setpoint(15.0)
        rig.motor.set_enable(True)
        with pytest.raises(RuntimeError, match="only change at standstill"):
            rig.set_crank_radius(0.01)
        while rig.motor.speed_hz() < 15.0:
            time.sleep(0.01)
        daq.start()
        d, _ = samples(daq, 0.5)
        daq.stop()
        daq.close()
    assert np.ptp(d) == pytest.approx(16384, rel=0.03)  # 5 mm: half the 10 mm amplitude


def test_a_connected_rig_loads_the_plan_whatever_it_is(tmp_path) -> None:
    """``ConnectedRig.load(plan)``: the simulated rig synthesises the plan's physics (its top mass)
    from then on, the crank angle carried over; the same plan again changes nothing; the radius
    actuator changes the radius at standstill only."""
    from drivers.sim.clock import VirtualClock
    from drivers.sim.daq_source import RigSource
    from station.config import to_rig_physics
    from station.run.request import RunRequest, StepSpec, plan_run
    from station.run.rig import connect
    from tests.conftest import station_config

    cfg = station_config(fast=True)

    async def go() -> None:
        async with connect(cfg, sim=True, sim_clock=VirtualClock()) as rig:
            assert rig.simulated and rig.health()["simulated"]
            src = rig.sim.source if rig.sim is not None else None
            assert isinstance(src, RigSource) and src.physics == to_rig_physics(cfg)
            src.configure(20_000.0, 10.0, 10.0)
            synth = src.synth
            assert synth is not None
            plan = plan_run(cfg, RunRequest(transducer_id=cfg.transducer.id, top_mass_kg=5.0,
                                            steps=[StepSpec(crank_frequency_hz=10.0, crank_radius_m=0.001)]))
            rig.load(plan)
            assert src.physics == to_rig_physics(plan.config) != to_rig_physics(cfg)
            assert src.synth is None and src._phi0 == synth.crank_angle_rad  # a new synthesiser, same angle
            src.configure(20_000.0, 10.0, 10.0)
            again = src.synth
            rig.load(plan)
            assert src.synth is again  # nothing to change
            await rig.radius.set_radius(0.002)
            assert rig.radius.radius_m == src.crank_radius_m == 0.002
            await rig.motor.start_watchdog(0.1)
            await rig.motor.set_ramp(100.0)
            await rig.motor.enable()
            await rig.motor.set_frequency(5.0)
            await rig.motor.wait_for_speed(5.0, timeout_s=2.0)
            with pytest.raises(RuntimeError, match=r"crank radius change refused: .*standstill"):
                await rig.radius.set_radius(0.003)
            assert src.crank_radius_m == 0.002
            await rig.motor.stop()
    asyncio.run(go())
