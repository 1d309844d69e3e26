"""Each real drive fails safe on the drive it names: the emulated drive starts with its factory settings
(communication-loss detection off, the command source on the panel, the VF-S11's reboot on a reset,
the V20 counting received process data), and the driver makes it safe -- it arms and reads back the
communication-loss stop before the first enable, or refuses naming the parameter; a lost link then
stops the crank within the configured time-out; the sequences are the ones the drives need.  In-process
on the virtual clock, except where the wire itself is the point (a command word sent once).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path

import pytest

from drivers.motor import (
    LinkPolicy,
    ModbusTransport,
    MotorController,
    MotorSafetyError,
    MotorStateError,
    MotorTimeoutError,
    load_profile,
)
from drivers.sim.clock import VirtualClock
from drivers.sim.motor_image import MotorRegisterImage
from drivers.sim.motor_inprocess import InProcessTransport
from drivers.sim.motor_model import MotorModel
from tests.drive_support import drive as factory_drive  # the emulated drive, as it leaves the factory

pytestmark = pytest.mark.waits  # the drives' watchdogs and time-outs in real time: about 5 s of wall time

REAL = ["toshiba-vf-s11", "automationdirect-gs2", "siemens-sinamics-v20", "cia402-modbus"]

def written(image: MotorRegisterImage) -> list[tuple[str, float, float]]:
    """Every register write the drive applied from now on: (register, value, model time)."""
    log: list[tuple[str, float, float]] = []
    image.observers.append(lambda name, value, _t: log.append((name, value, image.model.snapshot().time_s)))
    return log


async def cut_and_time_the_stop(motor: MotorController, model: MotorModel, clock: VirtualClock,
                                horizon_s: float) -> tuple[float | None, float | None]:
    """Pull the link; (seconds until the drive's watchdog expired, until standstill), None: not within
    ``horizon_s``."""
    transport = motor.transport
    assert isinstance(transport, InProcessTransport)
    transport.cut()
    t0 = clock.monotonic()
    expired = still = None
    while clock.monotonic() - t0 < horizon_s and still is None:
        await clock.asleep(0.01)
        snap = model.snapshot()
        if expired is None and snap.watchdog_expired:
            expired = snap.time_s - t0
        if snap.speed_hz == 0.0:
            still = snap.time_s - t0
    return expired, still


def panel_sources(image: MotorRegisterImage) -> None:
    """What a commissioning engineer sets so the drive listens to the bus (command and set-point
    source), leaving its communication-loss stop at the factory setting."""
    for s in image.profile.safety:
        if s.role in ("command_source", "setpoint_source") and s.value is not None:
            image.set_panel(s.register, s.value)


@pytest.mark.parametrize("name", REAL)
def test_out_of_the_box_the_drive_keeps_turning_when_the_link_is_lost(name: str) -> None:
    """The emulated drive is not safe by construction: enabled by raw writes without arming, with its
    factory communication-loss settings, it keeps the crank turning after the link is gone."""
    p = load_profile(name)

    async def body(motor: MotorController, model: MotorModel, image: MotorRegisterImage, clock: VirtualClock) -> None:
        panel_sources(image)
        t = motor.transport
        sp = p[p.setpoint]
        await t.write(sp.address, sp.encode(20.0), sp.name)
        for c in ("enable", "run"):
            for step in p.commands.sequences.get(c, ()):
                await t.write(p[step.register].address, p[step.register].words_of_raw(step.value), step.register)
                await clock.asleep(step.hold_s)
        await clock.asleep(20.0 / p.device.default_ramp_hz_per_s + 0.5)  # the factory ramp
        assert model.speed_hz() == pytest.approx(20.0, abs=0.01)
        expired, still = await cut_and_time_the_stop(motor, model, clock, 5.0)
        assert expired is None and still is None and model.speed_hz() == pytest.approx(20.0, abs=0.01)

    factory_drive(p, body)


@pytest.mark.parametrize("name", REAL)
def test_the_station_arms_the_comm_loss_stop_before_the_first_enable_and_a_lost_link_stops_the_crank(
        name: str) -> None:
    p = load_profile(name)
    wd = p.watchdog
    comm_loss = [s for s in p.safety if s.role.startswith("comm_loss_")]

    async def body(motor: MotorController, model: MotorModel, image: MotorRegisterImage, clock: VirtualClock) -> None:
        log = written(image)
        await motor.set_ramp(50.0)
        await motor.enable()  # arms first: nothing is enabled on a drive that was not made safe
        await motor.set_frequency(20.0)
        await motor.start_watchdog(0.2)
        await motor.wait_for_speed(20.0, timeout_s=5.0)
        first_command = next(i for i, (n, _, _) in enumerate(log) if n in p.commands.registers - {p.setpoint})
        before = {n: v for n, v, _ in log[:first_command]}
        assert before[wd.register] == pytest.approx(wd.timeout_s)  # the factory time-out is off or another
        for s in comm_loss:  # written before the first command word, or already so at the factory
            assert s.holds(before.get(s.register, s.default if s.default is not None else -1.0)), s
        assert motor.armed[wd.parameter] == pytest.approx(wd.timeout_s)
        assert all(s.parameter in motor.armed for s in p.safety)
        await clock.asleep(3.0)  # refreshed as the drive counts it: still turning
        assert model.speed_hz() == pytest.approx(20.0, abs=0.01) and not model.snapshot().watchdog_expired
        expired, still = await cut_and_time_the_stop(motor, model, clock, 10.0)
        assert expired is not None and expired <= wd.timeout_s + 1e-6, expired
        assert still is not None and still <= wd.timeout_s + 20.0 / p.device.stop_deceleration_hz_per_s + 0.05
        await motor.stop_watchdog()

    factory_drive(p, body)


REFUSALS = [
    # a setting only checked, set otherwise on the panel
    ("toshiba-vf-s11", lambda img: img.set_panel("upper_limit_frequency", 40.0), r"UL .*must be at least 50"),
    ("siemens-sinamics-v20", lambda img: img.set_panel("reference_frequency", 60.0),
     r"P2000 \(40016\) .*must be 50 \(Hz, the 100 % of HSW"),
    # a setting the drive answers but does not keep (a parameter lock)
    ("automationdirect-gs2", lambda img: img.locked.add("comm_loss_action"),
     r"P9.03 .*must be 1 \(warn and ramp to stop\), wrote 1, read back 0"),
    ("cia402-modbus", lambda img: img.locked.add("abort_connection_option"), r"0x6007 .*must be 3 \(quick stop"),
    ("toshiba-vf-s11", lambda img: img.locked.add("communication_timeout"), r"F803 .*must be 1 s"),
]


@pytest.mark.parametrize(("name", "spoil", "message"), REFUSALS)
def test_a_drive_that_does_not_hold_a_safety_setting_is_never_enabled(
        name: str, spoil: Callable[[MotorRegisterImage], None], message: str) -> None:
    p = load_profile(name)

    async def body(motor: MotorController, model: MotorModel, image: MotorRegisterImage, clock: VirtualClock) -> None:
        spoil(image)
        with pytest.raises(MotorSafetyError, match=message) as exc:
            await motor.enable()
        assert "the station does not enable the drive" in str(exc.value)
        assert exc.value.parameter in str(exc.value)
        with pytest.raises(MotorSafetyError):
            await motor.enable()  # and not on a second try either
        assert not model.snapshot().enabled and "enable" not in image.commands_seen

    factory_drive(p, body)


def test_the_station_refuses_a_run_on_a_drive_whose_upper_limit_is_too_low(tmp_path: Path) -> None:
    """Through the run procedure: the run fails before anything moves, naming UL and its value."""
    from station.config import parse_config
    from station.run.procedure import Procedure
    from station.run.request import RunRequest, StepSpec, plan_run
    from station.run.rig import connect
    from tests.drive_support import calibration_config

    cfg = parse_config(calibration_config("toshiba-vf-s11"), "test.yaml")
    steps = [StepSpec(crank_frequency_hz=s.crank_frequency_hz, crank_radius_m=s.crank_radius_m)
             for s in cfg.plan.steps]
    plan = plan_run(cfg, RunRequest(transducer_id=cfg.transducer.id, top_mass_kg=cfg.rig.top_mass_kg, steps=steps))

    async def go() -> tuple[str, str, list[str]]:
        async with connect(plan.config, sim=True, first_radius_m=steps[0].crank_radius_m,
                           sim_clock=VirtualClock()) as rig:
            assert rig.sim is not None
            rig.sim.image.set_panel("upper_limit_frequency", 45.0)
            outcome = await Procedure(plan, rig, tmp_path).execute()
            return outcome.exit_status, outcome.reason, list(rig.sim.image.commands_seen)

    status, reason, commands = asyncio.run(go())
    assert status == "failed" and "UL" in reason and "at least 50" in reason and "read back 45" in reason
    assert "enable" not in commands


# ------------------------------------------------------------------------------------------ watchdog refresh
def test_the_v20_watchdog_counts_received_process_data_not_reads() -> None:
    """F72: armed (40001 = P2014), the V20 trips when no set point arrives within the time-out, however
    often its status is read; the station's refresh rewrites the last set point and keeps it running."""
    p = load_profile("siemens-sinamics-v20")

    async def body(motor: MotorController, model: MotorModel, image: MotorRegisterImage, clock: VirtualClock) -> None:
        await motor.set_ramp(50.0)
        await motor.enable()
        await motor.set_frequency(20.0)
        await motor.start_watchdog(0.2)
        await motor.wait_for_speed(20.0, timeout_s=5.0)
        hsw = image.writes["hsw"]
        await clock.asleep(5.0)  # five time-outs long: refreshed
        assert model.speed_hz() == pytest.approx(20.0, abs=0.01) and not model.snapshot().watchdog_expired
        assert image.writes["hsw"] - hsw >= 20 and model.snapshot().setpoint_hz == pytest.approx(20.0, abs=0.01)
        await motor.stop_watchdog()
        t0 = clock.monotonic()
        while not model.snapshot().watchdog_expired and clock.monotonic() - t0 < 3.0:
            await motor.read_status()  # reads only: the V20 does not count them
            await clock.asleep(0.1)
        assert model.snapshot().watchdog_expired and clock.monotonic() - t0 <= p.watchdog.timeout_s + 0.15
        st = await motor.wait_for_speed(0.0, timeout_s=2.0, keep_watchdog=False)
        assert st.flags["fault"] and not st.flags["enabled"]

    factory_drive(p, body)


# ------------------------------------------------------------------------------------------ sequences
def test_the_vf_s11_reset_is_sent_once_and_the_drive_is_restored_after_its_reboot() -> None:
    p = load_profile("toshiba-vf-s11")

    async def body(motor: MotorController, model: MotorModel, image: MotorRegisterImage, clock: VirtualClock) -> None:
        await motor.arm()
        await motor.set_ramp(50.0)
        await motor.enable()
        await motor.set_frequency(20.0)
        await motor.wait_for_speed(20.0, timeout_s=5.0)
        log = written(image)
        await motor.emergency_stop()
        await motor.emergency_stop()  # latched: not sent again (a second one would reboot the drive)
        assert [v for n, v, _ in log if n == "command"] == [0xD000] and image.reboots == 0
        await motor.wait_for_speed(0.0, timeout_s=5.0, keep_watchdog=False)
        log.clear()
        t0 = clock.monotonic()
        await motor.reset_faults()  # no reply: the drive reboots; no error, no resend
        assert clock.monotonic() - t0 >= p.commands.reset_reboot_s
        assert image.reboots == 1
        words = [(n, v) for n, v, _ in log]
        assert words == [("command", 0xE000), ("frequency_command", 20.0), ("command", 0xC000)], words
        st = await motor.check_standstill()
        assert st.fault_code == 0 and not st.flags["estop"]
        await motor.set_frequency(10.0)
        await motor.enable()  # the restored drive runs again
        assert (await motor.wait_for_speed(10.0, timeout_s=5.0)).flags["enabled"]

    factory_drive(p, body)


def test_the_vf_s11_acc_dec_follow_the_fh_the_drive_holds() -> None:
    """ACC and DEC are times from 0 Hz to FH: a 20 Hz/s ramp is 2.5 s with FH = 50 Hz, 4.0 s with 80 Hz."""
    p = load_profile("toshiba-vf-s11")
    for fh, acc in ((50.0, 2.5), (80.0, 4.0)):

        async def body(motor: MotorController, model: MotorModel, image: MotorRegisterImage, clock: VirtualClock,
                       fh: float = fh, acc: float = acc) -> None:
            image.set_panel("maximum_frequency", fh)
            await motor.set_ramp(20.0)
            assert await motor.read("acceleration_time") == pytest.approx(acc)
            assert model.snapshot().ramp_hz_per_s == pytest.approx(20.0)  # the drive's own ramp

        factory_drive(p, body)


def test_the_gs2_stop_and_reset_leave_run_off_and_speed_zero() -> None:
    """A GS2 whose RUN register still says run starts again after a reset (the emulator plays it: the
    raw EF/reset without RUN = 0 restarts the crank); the profile's quick stop and reset leave RUN = 0
    and the speed reference 0, so the crank stays at rest."""
    p = load_profile("automationdirect-gs2")

    async def body(motor: MotorController, model: MotorModel, image: MotorRegisterImage, clock: VirtualClock) -> None:
        await motor.arm()
        t = motor.transport

        async def raw(register: str, value: int) -> None:
            await t.write(p[register].address, [value], register)
            await clock.asleep(0.05)

        await motor.set_ramp(50.0)
        await motor.enable()
        await motor.set_frequency(20.0)
        await motor.wait_for_speed(20.0, timeout_s=5.0)
        # the old way: EF, then reset, RUN left at 1
        await raw("serial_fault", 1)
        await motor.wait_for_speed(0.0, timeout_s=5.0)
        for register, value in (("serial_fault", 0), ("fault_reset", 1), ("fault_reset", 0)):
            await raw(register, value)
        await clock.asleep(1.0)
        assert model.speed_hz() > 10.0  # it started again on its own
        # the profile's way
        await motor.emergency_stop()
        assert await motor.read("run_command") == 0 and await motor.read("speed_reference") == 0
        await motor.wait_for_speed(0.0, timeout_s=5.0)
        await motor.reset_faults()
        await clock.asleep(2.0)
        st = await motor.check_standstill()
        assert st.fault_code == 0 and model.speed_hz() == 0.0
        assert await motor.read("run_command") == 0 and await motor.read("speed_reference") == 0

    factory_drive(p, body)


def test_the_gs2_direction_is_written_on_enable_and_read_back() -> None:
    p = load_profile("automationdirect-gs2")

    async def body(motor: MotorController, model: MotorModel, image: MotorRegisterImage, clock: VirtualClock) -> None:
        await motor.arm()
        image.set_panel("direction_command", 1)  # reverse, left over from the panel
        await motor.enable()
        assert await motor.read("direction_command") == 0 and model.snapshot().enabled
        await motor.stop()
        image.set_panel("direction_command", 1)
        image.locked.add("direction_command")  # a drive that does not take it
        with pytest.raises(MotorStateError, match=r"direction_command.*wrote 0, read back 1"):
            await motor.enable()

    factory_drive(p, body)


# ------------------------------------------------------------------------------------------ sent once
class SilentOnWrites:
    """A Modbus TCP peer that answers reads (zeros) and never answers a write: counts what arrives."""

    def __init__(self) -> None:
        self.writes = 0

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                head = await reader.readexactly(6)
                body = await reader.readexactly(int.from_bytes(head[4:6], "big"))
                if body[1] in (0x06, 0x10):
                    self.writes += 1
                    continue
                qty = int.from_bytes(body[4:6], "big")
                reply = body[:2] + bytes([2 * qty]) + bytes(2 * qty)
                writer.write(head[:4] + len(reply).to_bytes(2, "big") + reply)
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionResetError):
            return


@pytest.mark.slow
def test_a_command_word_is_sent_once_a_set_point_may_be_sent_again() -> None:
    """With two retries in the link policy, a command word that gets no reply went out once (the
    error says so); the set point, which the profile lists as idempotent, is sent three times."""
    p = load_profile("toshiba-vf-s11")
    peer = SilentOnWrites()

    async def run() -> None:
        server = await asyncio.start_server(peer._handle, "127.0.0.1", 0)
        host, port = server.sockets[0].getsockname()[:2]
        motor = MotorController(p, clock=VirtualClock())
        await motor.connect(ModbusTransport.tcp(host, port, policy=LinkPolicy(timeout_s=0.2, retries=2)))
        with pytest.raises(MotorTimeoutError, match=r"register 'command'.*1 attempt.*sent once, not repeated"):
            await motor.emergency_stop()
        assert peer.writes == 1
        with pytest.raises(MotorTimeoutError, match=r"register 'frequency_command'.*3 attempt"):
            await motor.set_frequency(10.0)
        assert peer.writes == 4
        await motor.close()
        server.close()

    asyncio.run(run())


@pytest.mark.slow
def test_the_vf_s11_reset_over_modbus_tcp_gets_no_reply_is_not_resent_and_the_drive_comes_back() -> None:
    """On the wire (the emulator's Modbus TCP server, real time): the reset frame gets no reply while
    the drive reboots; the driver does not send it again, waits out the reboot and restores the drive."""
    from drivers.sim.rig import SimRig

    p = load_profile("toshiba-vf-s11")
    with SimRig(seed=3, profile=p, rtu=False) as rig:
        log = written(rig.image)

        async def run() -> None:
            motor = MotorController(p)
            await motor.connect(ModbusTransport.tcp(*rig.addresses.modbus_tcp,
                                                    policy=LinkPolicy(timeout_s=0.5, retries=2)))
            await motor.arm()
            rig.motor.emergency_stop()  # the drive's E trip, at standstill
            await motor.reset_faults()
            st = await motor.check_standstill()
            assert st.fault_code == 0
            await motor.close()

        asyncio.run(run())
        assert rig.image.reboots == 1 and rig.modbus_faults.dropped >= 1
        assert [v for n, v, _ in log if n == "command"] == [0xE000, 0xC000]
        assert rig.image.write_requests["command"] == 2  # the reset and the restore: nothing sent again
