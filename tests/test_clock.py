"""The virtual clock: time jumps to the next wake-up only while every participant waits, so
threads and tasks keep step; the in-process DAQ backend streams on it without loss."""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
import pytest

from drivers.clock import REAL_CLOCK
from drivers.daq.bridge import DaqBridge
from drivers.daq.protocol import SampleBlock
from drivers.sim.clock import VirtualClock
from drivers.sim.daq_source import SineSource
from drivers.sim.rig import SimRig


def test_sleeps_take_virtual_time_not_real_time() -> None:
    clock = VirtualClock(start_s=50.0)
    t_real = time.monotonic()
    clock.sleep(3600.0)  # an hour
    assert clock.monotonic() == pytest.approx(3650.0)
    assert time.monotonic() - t_real < 5.0  # a bound for a loaded machine, far from the hour


def test_threads_and_tasks_wake_in_virtual_time_order() -> None:
    clock = VirtualClock(start_s=0.0, hold_s=10.0)  # the main thread's hold outlasts a loaded machine
    woke: list[tuple[str, float]] = []
    lock = threading.Lock()

    def sleeper(name: str, dt: float, n: int) -> None:
        for _ in range(n):
            clock.sleep(dt)
            with lock:
                woke.append((name, clock.monotonic()))

    async def task_sleeper() -> None:
        for _ in range(4):
            await clock.asleep(0.25)
            with lock:
                woke.append(("task", clock.monotonic()))

    threads = [threading.Thread(target=sleeper, args=("a", 0.3, 3)),
               threading.Thread(target=sleeper, args=("b", 0.2, 5)),
               threading.Thread(target=asyncio.run, args=(task_sleeper(),))]
    clock.hold()  # time stands still until all three wait
    for th in threads:
        th.start()
    time.sleep(0.2)
    clock.sleep(2.0)
    for th in threads:
        th.join(10)
    expect = sorted([("a", 0.3 * k) for k in (1, 2, 3)] + [("b", 0.2 * k) for k in (1, 2, 3, 4, 5)]
                    + [("task", 0.25 * k) for k in (1, 2, 3, 4)], key=lambda x: x[1])
    assert [round(t, 9) for _, t in woke] == [round(t, 9) for _, t in expect]  # in time order
    for name in ("a", "b", "task"):
        assert [round(t, 9) for n, t in woke if n == name] == [round(t, 9) for n, t in expect if n == name]


def test_an_awake_participant_holds_the_clock() -> None:
    """While one thread works between two sleeps, time does not move for the others."""
    clock = VirtualClock(start_s=0.0, hold_s=5.0)
    seen: list[float] = []

    def worker() -> None:
        clock.sleep(1.0)
        t = clock.monotonic()
        time.sleep(0.3)  # real work, no wait on the clock
        seen.append(clock.monotonic() - t)
        clock.sleep(1.0)

    def ticker() -> None:
        for _ in range(50):
            clock.sleep(0.01)

    threads = [threading.Thread(target=worker), threading.Thread(target=ticker)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(20)
    assert seen == [0.0]
    assert clock.monotonic() == pytest.approx(2.0)


def test_wait_for_returns_on_notify_without_time_passing() -> None:
    clock = VirtualClock(start_s=0.0, hold_s=10.0)
    flag = threading.Event()
    result: list[tuple[bool, float]] = []

    def waiter() -> None:
        result.append((clock.wait_for(flag.is_set, 10.0), clock.monotonic()))

    th = threading.Thread(target=waiter)
    clock.hold()  # without a participant awake, the waiter's 10 s would pass at once
    th.start()
    time.sleep(0.05)
    flag.set()
    clock.notify()
    th.join(5)
    assert result == [(True, 0.0)]
    # and without a notify the time-out is virtual
    assert clock.wait_for(lambda: False, 2.5) is False
    assert clock.monotonic() >= 2.5


def test_real_clock_is_wall_time() -> None:
    t0 = REAL_CLOCK.monotonic()
    REAL_CLOCK.sleep(0.02)
    assert REAL_CLOCK.monotonic() - t0 >= 0.02
    assert REAL_CLOCK.wait_for(lambda: True, 1.0) is True


def test_inprocess_daq_streams_on_the_virtual_clock_without_loss() -> None:
    """Ten virtual seconds at 20 kHz through the real DAQ driver on the in-process link."""
    clock = VirtualClock()
    with SimRig(seed=6, wire=False, clock=clock, source=SineSource()) as rig:
        rig.motor.set_watchdog_timeout(60.0)  # 0 (off) is refused with the drive enabled
        rig.motor.set_ramp(100.0)
        rig.motor.set_setpoint(20.0)
        rig.motor.set_enable(True)
        daq = DaqBridge()
        daq.connect(rig.daq_link())
        daq.configure(rate_hz=20_000, frame_samples=256)
        t0 = clock.monotonic()
        daq.start()
        samples = 0
        while clock.monotonic() - t0 < 10.0:
            ev = daq.get_event(0.0)
            if ev is None:
                clock.sleep(0.01)
                continue
            assert isinstance(ev, SampleBlock) and ev.first_index == samples
            if samples > 0.2 * 20_000:  # the crank turns: both channels move
                assert np.abs(ev.displacement).max() > 0 and np.abs(ev.force).max() > 0
            samples += ev.displacement.size
        summary = daq.stop()
        while (ev := daq.get_event(0.0)) is not None:
            samples += ev.displacement.size
        closer = threading.Thread(target=daq.close)  # its reader thread waits on the clock: keep it moving
        closer.start()
        while closer.is_alive():
            clock.sleep(0.02)
    assert summary.stats.crc_errors == 0 and rig.daq.lost == []
    assert samples == summary.samples_sent
    assert samples == pytest.approx(10.0 * 20_000, abs=2 * 256 + 0.05 * 20_000)


def test_a_participant_out_of_sight_slows_time_to_real_time_without_deadlock() -> None:
    """One thread holds the clock and then works without waiting on it (longer than ``hold_s``):
    time goes on, but no faster than real time, so its deadlines are no tighter than for real."""
    t_real = time.monotonic()
    clock = VirtualClock(start_s=0.0, hold_s=0.1)
    held = threading.Event()
    seen: list[tuple[float, float]] = []

    def blind() -> None:
        clock.hold()
        held.set()
        time.sleep(0.5)  # work the clock does not see
        seen.append((clock.monotonic(), time.monotonic() - t_real))

    def ticker() -> None:
        for _ in range(100):
            clock.sleep(0.1)

    a = threading.Thread(target=blind)
    a.start()
    held.wait(5)
    b = threading.Thread(target=ticker)
    b.start()
    a.join(10)
    b.join(20)
    virtual, real = seen[0]
    assert virtual <= real + 0.1 + 1e-9  # at most one tick ahead of real time
    assert clock.monotonic() == pytest.approx(10.0)  # and no deadlock: the ticker finished
    assert clock.released >= 1


@pytest.mark.parametrize("started_on_the_clock", [True, False])
def test_a_task_started_on_the_clock_runs_before_time_moves(started_on_the_clock: bool) -> None:
    """A task started with ``start_task`` is awake until it first waits: its caller's wait cannot let
    time jump past it, even while the loop is busy before the task's first step (the drive's watchdog
    keeper, started just before the procedure sleeps).  A plain ``asyncio.create_task`` is unknown to
    the clock until then, and time runs past it: its first step sees the caller's wake-up time."""
    clock = VirtualClock(start_s=0.0, hold_s=10.0)
    first_step_at: list[float] = []

    async def keeper() -> None:
        first_step_at.append(clock.monotonic())
        await clock.asleep(1.0)

    async def go() -> None:
        asyncio.get_running_loop().call_soon(time.sleep, 0.5)  # the loop busy before the task's first step
        task = (clock.start_task(keeper(), "keeper") if started_on_the_clock
                else asyncio.create_task(keeper()))
        await clock.asleep(10.0)
        task.cancel()  # (awaiting its end would hold the clock: this task does not wait on it meanwhile)
        await asyncio.gather(task, return_exceptions=True)

    asyncio.run(go())
    assert first_step_at == ([0.0] if started_on_the_clock else [10.0])
