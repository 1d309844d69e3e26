"""The DAQ emulator's samples are a function of their index: a host that stalls the emulator (it
computes 0.5 s of samples at once, late) delays them but does not change them, even while the crank
ramps from one step to the next (the frequency of each sample is the motor's at that sample's instant)."""

from __future__ import annotations

import numpy as np

from drivers.daq.protocol import SampleBlock, StreamDecoder, encode_command
from drivers.motor.profile import DeviceDefaults
from drivers.rig.presets import paper_5kN_physics
from drivers.sim.daq_emulator import DaqEmulator
from drivers.sim.daq_source import RigSource
from drivers.sim.motor_model import MotorModel


class StepClock:
    """A clock the test moves by hand (s)."""

    def __init__(self) -> None:
        self.t = 100.0

    def monotonic(self) -> float:
        return self.t

    def notify(self) -> None:
        pass


def _stream(stall: tuple[float, float] | None) -> bytes:
    """The bytes an emulator sends over 3 s: the crank ramps 0 -> 8 Hz at 20 Hz/s from 0.5 s and
    8 -> 14 Hz from 1.6 s; the emulator is called every 5 ms except inside ``stall`` (start, end)."""
    clock = StepClock()
    motor = MotorModel(DeviceDefaults(), clock=clock.monotonic)
    motor.set_watchdog_timeout(100.0)
    source = RigSource(paper_5kN_physics(), seed=7, crank_radius_m=0.01)
    emu = DaqEmulator(None, source, motor.speed_hz, clock=clock).start()  # type: ignore[arg-type]
    emu.feed(encode_command("START"))
    out = bytearray()
    t0 = clock.t
    for k in range(1, 601):
        clock.t = t0 + 0.005 * k
        if k == 100:
            motor.set_ramp(20.0)
            motor.set_setpoint(8.0)
            motor.set_enable(True)
        if k == 320:
            motor.set_setpoint(14.0)
        if stall is not None and stall[0] <= clock.t - t0 < stall[1]:
            continue
        out += emu.pull(1 << 22)
    return bytes(out)


def _samples(stream: bytes) -> tuple[np.ndarray, np.ndarray]:
    dec = StreamDecoder()
    blocks = [e for e in dec.feed(stream) if isinstance(e, SampleBlock)]
    return (np.concatenate([b.displacement for b in blocks]), np.concatenate([b.force for b in blocks]))


def test_a_stalled_emulator_produces_the_same_samples_as_a_prompt_one() -> None:
    prompt = _samples(_stream(None))
    stalled = _samples(_stream((1.55, 2.06)))  # 0.51 s without a call, across the second ramp
    n = len(prompt[0])
    assert n > 2.5 * 20_000 and len(stalled[0]) == n
    assert np.ptp(prompt[0].astype(int)) > 10_000  # the crank turns: a real signal, not silence
    np.testing.assert_array_equal(stalled[0], prompt[0])
    np.testing.assert_array_equal(stalled[1], prompt[1])


def test_the_motor_knows_its_speed_at_past_instants() -> None:
    clock = StepClock()
    motor = MotorModel(DeviceDefaults(), clock=clock.monotonic)
    motor.set_watchdog_timeout(100.0)
    motor.set_ramp(10.0)
    motor.set_setpoint(5.0)
    motor.set_enable(True)
    t0 = clock.t
    clock.t = t0 + 2.0
    motor.set_setpoint(2.0)
    clock.t = t0 + 4.0
    assert motor.speed_hz() == 2.0
    for dt, want in ((0.0, 0.0), (0.25, 2.5), (0.5, 5.0), (1.9, 5.0), (2.1, 4.0), (2.3, 2.0), (9.0, 2.0)):
        assert abs(motor.speed_hz(t0 + dt) - want) < 1e-12, dt
