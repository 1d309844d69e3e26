"""Unit tests of the emulated motor's dynamics (stepped clock) and its register image."""

from __future__ import annotations

import math

import pytest

from drivers.motor.profile import load_profile
from drivers.sim.motor_image import DEVICE_FAILURE, ILLEGAL_ADDRESS, ILLEGAL_VALUE, MotorRegisterImage
from drivers.sim.motor_model import FAULT_ESTOP, FAULT_WATCHDOG, MotorModel


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def model(clock: Clock) -> MotorModel:
    return MotorModel(load_profile().device, clock=clock)


def test_ramp_to_setpoint_and_exact_angle(model: MotorModel, clock: Clock) -> None:
    model.set_watchdog_timeout(60.0)  # 0 (off) is refused with the drive enabled
    model.set_ramp(5.0)
    model.set_setpoint(10.0)
    model.set_enable(True)
    clock.t += 1.0
    assert model.snapshot().speed_hz == pytest.approx(5.0)
    clock.t += 2.0  # reaches 10 Hz after 2 s, then 1 s at 10 Hz
    s = model.snapshot()
    assert s.speed_hz == 10.0
    assert s.angle_rad == pytest.approx(2 * math.pi * (0.5 * 10 * 2 + 10 * 1))  # 20 revolutions
    model.set_enable(False)
    clock.t += 1.0
    assert model.snapshot().speed_hz == pytest.approx(5.0)
    clock.t += 5.0
    assert model.snapshot().speed_hz == 0.0


def test_watchdog_expiry_stops_the_motor_at_the_deadline(model: MotorModel, clock: Clock) -> None:
    model.set_watchdog_timeout(0.5)
    model.set_ramp(100.0)
    model.set_setpoint(20.0)
    model.set_enable(True)
    for _ in range(10):  # refreshed in time: keeps running
        clock.t += 0.4
        model.refresh_watchdog()
    assert model.snapshot().fault_code == 0 and model.snapshot().speed_hz == 20.0
    clock.t += 0.5 + 0.2  # expired 0.2 s ago: decelerating at 50 Hz/s since the deadline
    s = model.snapshot()
    assert s.fault_code == FAULT_WATCHDOG and s.watchdog_expired and not s.enabled
    assert s.speed_hz == pytest.approx(20.0 - 50.0 * 0.2)
    clock.t += 1.0
    assert model.snapshot().speed_hz == 0.0


def test_limits_estop_and_fault_reset(model: MotorModel, clock: Clock) -> None:
    with pytest.raises(ValueError, match="outside"):
        model.set_setpoint(100.01)
    with pytest.raises(ValueError, match="outside"):
        model.set_ramp(0.0)
    model.set_watchdog_timeout(60.0)  # 0 (off) is refused with the drive enabled
    model.set_ramp(50.0)
    model.set_setpoint(10.0)
    model.set_enable(True)
    clock.t += 1.0
    model.emergency_stop()
    with pytest.raises(PermissionError, match="while turning"):
        model.reset_faults()
    with pytest.raises(PermissionError, match="reset it first"):
        model.set_enable(True)
    clock.t += 0.1
    s = model.snapshot()
    assert s.fault_code == FAULT_ESTOP and s.estop and s.speed_hz == pytest.approx(5.0)
    clock.t += 1.0
    model.reset_faults()
    assert model.snapshot().fault_code == 0
    model.set_enable(True)


def test_register_image_words_and_exception_codes(model: MotorModel, clock: Clock) -> None:
    m = load_profile()
    img = MotorRegisterImage(m, model)
    assert img.read(106, 1) == [10000]  # max_frequency 100.00 Hz
    assert img.read(50, 1) == ILLEGAL_ADDRESS
    assert img.read(106, 2) == ILLEGAL_ADDRESS  # runs past the map
    assert img.write(1, [15000]) == ILLEGAL_VALUE  # 150 Hz > max
    assert img.write(100, [1]) == ILLEGAL_ADDRESS  # read-only
    assert img.write(105, [1]) == ILLEGAL_ADDRESS  # second word of a uint32
    assert img.write(0, [2]) == ILLEGAL_VALUE
    assert img.write(4, [0]) is None  # watchdog off: allowed while disabled ...
    assert img.write(0, [1]) == DEVICE_FAILURE  # ... but then the drive cannot be enabled
    assert img.write(4, [60000]) is None  # 60 s
    assert img.write(2, [5000, 1]) is None  # ramp 50 Hz/s + watchdog in one FC16 write
    assert img.write(1, [2000]) is None and img.write(0, [1]) is None
    clock.t += 1.0
    speed, angle, status, fault, rev_hi, rev_lo = img.read(100, 6)
    assert speed == 2000 and status & 0b111 == 0b111 and fault == 0
    revs = 0.5 * 20 * 0.4 + 20 * 0.6  # 16 revolutions exactly
    assert (rev_hi << 16 | rev_lo) == int(revs) and angle == 0
    model.inject_fault(3)
    assert img.read(103, 1) == [3]
    assert img.write(0, [1]) == DEVICE_FAILURE


def test_a_drive_that_ignores_stops_keeps_turning_until_repaired(model: MotorModel, clock: Clock) -> None:
    img = MotorRegisterImage(load_profile(), model)
    seen: list[tuple[str, float]] = []
    img.observers.append(lambda name, value, t: seen.append((name, value)))
    model.set_watchdog_timeout(0.5)
    model.set_ramp(50.0)
    model.set_setpoint(10.0)
    model.set_enable(True)
    model.ignore_stops()
    clock.t += 1.0  # at 10 Hz; the watchdog expired meanwhile and is ignored too
    assert img.write(img.map["emergency_stop"].address, [1]) is None  # the command is taken ...
    assert seen == [("emergency_stop", 1.0)]
    clock.t += 5.0
    s = model.snapshot()
    assert s.speed_hz == pytest.approx(10.0) and s.fault_code != 0  # ... and ignored: still 10 Hz
    with pytest.raises(PermissionError):
        model.reset_faults()  # refused while turning, as on a healthy drive
    model.ignore_stops(False)  # repaired: the latched fault stops it at the stop ramp
    clock.t += 10.0 / model.device.stop_deceleration_hz_per_s + 0.01
    assert model.snapshot().speed_hz == 0.0
    model.reset_faults()


def test_without_the_fault_the_same_stop_stops_the_crank(model: MotorModel, clock: Clock) -> None:
    model.set_watchdog_timeout(60.0)
    model.set_ramp(50.0)
    model.set_setpoint(10.0)
    model.set_enable(True)
    clock.t += 1.0
    model.emergency_stop()
    clock.t += 10.0 / model.device.stop_deceleration_hz_per_s + 0.01
    assert model.snapshot().speed_hz == 0.0
