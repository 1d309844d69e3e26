"""Integration: the real motor driver against the emulated controller (Modbus TCP, RTU, in-process).

The controller's logic (watchdog, faults, emergency stop, state checks) runs in-process on a virtual
clock (``vrig``): the emulator integrates its ramps and expires its watchdog on that clock, so seconds
of ramps take milliseconds.  Framing, lost replies and lost links stay on the wire in real time."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator

import pytest

from drivers.motor import (
    LinkPolicy,
    ModbusTransport,
    MotorController,
    MotorExceptionReplyError,
    MotorFaultError,
    MotorLinkError,
    MotorStateError,
    MotorTimeoutError,
    MotorValueError,
    RegisterTransport,
)
from drivers.sim import SimRig
from drivers.sim.clock import VirtualClock

pytestmark = pytest.mark.waits  # reply time-outs over a pty and TCP: about 9 s of wall time, under 1 s of CPU

# the reply timeout leaves room for a loaded machine: the emulator runs in this test's process, and with
# four pytest workers on two cores a reply over the pty once took more than 0.3 s (a write is not repeated)
FAST = LinkPolicy(timeout_s=1.0, retries=1, backoff_initial_s=0.05, reconnect_attempts=3)


@pytest.fixture
def rig() -> Iterator[SimRig]:
    with SimRig(seed=2) as r:
        yield r


def transport(rig: SimRig, kind: str) -> RegisterTransport:
    if kind == "tcp":
        return ModbusTransport.tcp(*rig.addresses.modbus_tcp, policy=FAST)
    if kind == "rtu":
        assert rig.addresses.modbus_rtu is not None
        return ModbusTransport.rtu(rig.addresses.modbus_rtu, parity="N", policy=FAST)  # 8N2: a pty refuses even parity
    return rig.motor_transport()


@pytest.fixture
def vrig() -> Iterator[SimRig]:
    """The simulated rig without a wire, on a virtual clock."""
    rig = SimRig(seed=2, wire=False, clock=VirtualClock()).start()
    try:
        yield rig
    finally:
        rig.close()


async def connected(rig: SimRig, kind: str = "tcp") -> MotorController:
    """The driver connected to ``rig`` over ``kind`` (the in-process transport for a rig without a wire),
    keeping the rig's clock."""
    motor = MotorController(clock=rig.clock)
    await motor.connect(transport(rig, kind if rig.wire else "inprocess"))
    return motor


@pytest.mark.parametrize("kind", ["tcp", "rtu", "inprocess"])
@pytest.mark.slow
def test_ramp_to_setpoint_and_back(request: pytest.FixtureRequest, kind: str) -> None:
    """Over Modbus TCP and RTU in real time; in-process on a virtual clock (the driver keeps the
    rig's clock: its status stamps, its watchdog keeper and ``wait_for_speed`` run on it)."""
    if kind == "inprocess":
        clock = VirtualClock()
        rig = SimRig(seed=2, wire=False, clock=clock).start()
        request.addfinalizer(rig.close)
    else:
        rig = request.getfixturevalue("rig")

    async def run() -> None:
        motor = MotorController(clock=rig.clock)
        await motor.connect(transport(rig, kind))
        clock = motor.clock
        await motor.start_watchdog(0.1)
        await motor.set_ramp(20.0)
        await motor.enable()
        await motor.set_frequency(10.0)
        t0 = clock.monotonic()
        mid = await motor.read_status()
        await clock.asleep(0.1)
        mid2 = await motor.read_status()
        # ramping at 20 Hz/s (the emulator integrates exactly); each reading is known to within its
        # round trip, plus the 0.01 Hz register resolution
        slack = 20.0 * (mid.round_trip_s + mid2.round_trip_s) / 2 + 0.02
        assert mid2.actual_speed_hz - mid.actual_speed_hz == pytest.approx(20.0 * (mid2.time_s - mid.time_s),
                                                                           abs=slack)
        assert mid2.flags["ramping"] and not mid2.flags["at_setpoint"]
        await motor.wait_for_speed(10.0, timeout_s=3.0)  # within the register's 0.01 Hz
        assert 0.4 < clock.monotonic() - t0 < 2.0
        await clock.asleep(0.05)  # at_setpoint is exact equality: one poll later it is there
        st = await motor.read_status()
        assert st.flags["at_setpoint"] and st.flags["running"] and st.fault_code == 0
        await motor.stop()
        await motor.wait_for_speed(0.0, timeout_s=3.0)
        await clock.asleep(0.05)
        down = await motor.read_status()
        assert not down.flags["running"] and not down.flags["enabled"] and down.fault_code == 0
        assert rig.motor.snapshot().speed_hz == 0.0
        await motor.close()

    asyncio.run(run())


def test_stopping_the_watchdog_refresh_stops_the_motor(vrig: SimRig) -> None:
    rig, clock = vrig, vrig.clock

    async def run() -> None:
        motor = await connected(rig)
        await motor.set_watchdog_timeout(0.4)
        await motor.set_ramp(50.0)
        await motor.enable()
        await motor.set_frequency(20.0)
        await motor.start_watchdog(0.1)
        await motor.wait_for_speed(20.0, timeout_s=3.0)
        await clock.asleep(0.6)  # longer than the timeout, but refreshed: still running
        st = await motor.read_status()
        assert st.actual_speed_hz == pytest.approx(20.0) and st.fault_code == 0
        await motor.stop_watchdog()
        await clock.asleep(0.5)
        st = await motor.read_status()
        assert st.fault_name == "watchdog_expired" and st.flags["watchdog_expired"] and st.flags["fault"]
        assert st.actual_speed_hz < 20.0
        st = await motor.wait_for_speed(0.0, timeout_s=2.0, keep_watchdog=False)
        assert not st.flags["enabled"]
        with pytest.raises(MotorExceptionReplyError, match="SERVER DEVICE FAILURE") as info:
            await motor.enable()  # refused until the fault is reset
        assert info.value.register == "enable"
        await clock.asleep(0.05)  # the register reads 0 below 0.005 Hz; the reset needs true standstill
        await motor.reset_faults()
        assert (await motor.read_status()).fault_code == 0
        await motor.close()

    asyncio.run(run())


def test_exception_replies_and_local_limits_are_typed_errors(rig: SimRig) -> None:
    async def run() -> None:
        motor = await connected(rig)
        with pytest.raises(MotorValueError, match=r"expected 0..100 Hz, got 150.0 Hz"):
            await motor.set_frequency(150.0)
        with pytest.raises(MotorValueError, match=r"expected 0..100 Hz, got 150.0 Hz"):
            await motor.write("frequency_setpoint", 150.0)  # refused before sending
        reg = motor.map["frequency_setpoint"]
        with pytest.raises(MotorExceptionReplyError) as info:  # the controller refuses it too
            await motor.transport.write(reg.address, reg.encode(150.0), reg.name)
        assert (info.value.register, info.value.exception_code) == ("frequency_setpoint", 3)
        with pytest.raises(MotorValueError, match="read-only"):
            await motor.write("actual_speed", 1.0)
        rig.modbus_faults.exception_replies(0x06, n=1)
        with pytest.raises(MotorExceptionReplyError, match="status block") as info:
            await motor.read_status()
        assert info.value.exception_code == 6
        assert (await motor.read("max_frequency")) == pytest.approx(100.0)
        await motor.close()

    asyncio.run(run())


@pytest.mark.parametrize("kind", ["tcp", "rtu"])
@pytest.mark.slow
def test_timeouts_are_retried_then_reported(rig: SimRig, kind: str) -> None:
    async def run() -> None:
        motor = await connected(rig, kind)
        rig.modbus_faults.drop_replies(1)  # one lost reply: the retry succeeds
        t0 = time.monotonic()
        assert (await motor.read("max_frequency")) == pytest.approx(100.0)
        assert time.monotonic() - t0 >= FAST.timeout_s
        rig.modbus_faults.drop_replies(2)  # every attempt lost
        with pytest.raises(MotorTimeoutError, match=r"register 'crank_angle'.*2 attempt"):
            await motor.read("crank_angle")
        assert rig.modbus_faults.dropped == 3
        assert (await motor.read("max_frequency")) == pytest.approx(100.0)
        await motor.close()

    asyncio.run(run())


@pytest.mark.slow
def test_lost_link_is_typed_the_emulator_stops_and_the_driver_reconnects(rig: SimRig) -> None:
    async def run() -> None:
        motor = await connected(rig)
        await motor.set_watchdog_timeout(0.3)
        await motor.set_ramp(100.0)
        await motor.enable()
        await motor.set_frequency(10.0)
        await motor.wait_for_speed(10.0, timeout_s=2.0)
        await asyncio.to_thread(rig.run, rig.modbus.stop_tcp())
        with pytest.raises(MotorLinkError, match=r"register 'watchdog'.*3 reconnect attempts failed"):
            await motor.refresh_watchdog()
        await asyncio.sleep(0.5)
        assert rig.motor.snapshot().fault_code == 1  # the controller's watchdog stopped the motor
        await asyncio.to_thread(rig.run, rig.modbus.restart_tcp())
        st = await motor.read_status()  # reconnects with back-off
        assert st.fault_name == "watchdog_expired"
        await motor.close()

    asyncio.run(run())


def test_injected_motor_fault_and_emergency_stop(vrig: SimRig) -> None:
    rig = vrig

    async def run() -> None:
        motor = await connected(rig)
        await motor.set_watchdog_timeout(60.0)  # 0 (off) is refused with the drive enabled
        await motor.set_ramp(100.0)
        await motor.enable()
        await motor.set_frequency(30.0)
        await motor.wait_for_speed(30.0, timeout_s=2.0)
        assert (await motor.require_no_fault()).fault_code == 0
        rig.motor.inject_fault(3)
        st = await motor.read_status()
        assert (st.fault_code, st.fault_name) == (3, "overcurrent") and st.flags["fault"]
        with pytest.raises(MotorFaultError, match=r"fault 3 \(overcurrent\)"):
            await motor.require_no_fault()
        await motor.wait_for_speed(0.0, timeout_s=2.0)
        await motor.reset_faults()
        await motor.enable()
        await motor.wait_for_speed(30.0, timeout_s=2.0)
        await motor.emergency_stop()
        st = await motor.read_status()
        assert st.flags["estop"] and st.fault_name == "emergency_stop"
        with pytest.raises(MotorExceptionReplyError, match="register 'fault_reset'"):
            await motor.reset_faults()  # refused while still turning
        await motor.wait_for_speed(0.0, timeout_s=2.0)
        await motor.reset_faults()
        assert (await motor.read("emergency_stop")) == 0
        await motor.close()

    asyncio.run(run())


def test_state_check_reports_faults_without_clearing_them(vrig: SimRig) -> None:
    rig = vrig

    async def run() -> None:
        motor = await connected(rig)
        st = await motor.check_standstill()
        assert st.standstill and st.fault_code == 0 and st.describe() == "standstill, disabled, no fault"
        await motor.emergency_stop()
        with pytest.raises(MotorFaultError, match=r"fault 2 \(emergency_stop\)"):
            await motor.check_standstill()
        st = await motor.read_state()
        assert st.estop_latched and st.fault_code == 2  # still latched: reported, not cleared
        assert "fault 2 (emergency_stop), emergency stop latched" in st.describe()
        await motor.reset_faults()  # the operator's decision
        await motor.set_watchdog_timeout(60.0)
        await motor.set_ramp(100.0)
        await motor.enable()
        with pytest.raises(MotorStateError, match="expected standstill and disabled, found standstill, enabled"):
            await motor.check_standstill()
        await motor.set_frequency(10.0)
        await motor.wait_for_speed(10.0, timeout_s=2.0)
        with pytest.raises(MotorStateError, match="found turning at 10 Hz, enabled"):
            await motor.check_standstill()
        await motor.stop()
        await motor.wait_for_speed(0.0, timeout_s=2.0)
        assert (await motor.check_standstill()).fault_code == 0
        await motor.close()

    asyncio.run(run())
