"""The drive's one link in the rig process takes turns most urgent first: a stop before the watchdog
refresh, the refresh before the web process's questions (``station.rigproc.turns``).  Checked on the
lock itself and on the rig process against the emulated drive, with a queue of the web process's reads
in front of the keeper's refresh and of the stop: each goes out after at most the one exchange already
on the wire (first-come, it would wait for all of them)."""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import Sequence

from drivers.motor import MotorController
from drivers.motor.profile import load_profile
from drivers.sim.clock import VirtualClock
from drivers.sim.motor_image import MotorRegisterImage
from drivers.sim.motor_inprocess import InProcessTransport
from drivers.sim.motor_model import MotorModel
from station.rigproc.serve import RigProcess
from station.rigproc.turns import OneAtATime, TurnLock, Urgency
from tests.drive_support import RIG_SPEC

WEB_READS = 20
WEB = "status (web)"


def test_the_lock_serves_the_most_urgent_waiter_first_then_in_order_and_survives_a_cancelled_one() -> None:
    order: list[str] = []

    async def body() -> None:
        lock = TurnLock()

        async def take(name: str, level: Urgency) -> None:
            async with lock.turn(level):
                order.append(name)
                await asyncio.sleep(0)

        async with lock.turn(Urgency.WEB):
            tasks = [asyncio.create_task(take(n, lv)) for n, lv in (
                ("web-1", Urgency.WEB), ("web-2", Urgency.WEB), ("keeper", Urgency.KEEPER),
                ("gone", Urgency.STOP), ("stop", Urgency.STOP), ("web-3", Urgency.WEB))]
            await asyncio.sleep(0)
            assert lock.waiting() == 6
            tasks[3].cancel()  # a stop that gave up waiting takes no turn and keeps none
            await asyncio.sleep(0)
        await asyncio.gather(*tasks, return_exceptions=True)
        assert not lock.held and lock.waiting() == 0
        async with lock.turn(Urgency.WEB):  # free again: taken at once
            order.append("after")

    asyncio.run(body())
    assert order == ["stop", "keeper", "web-1", "web-2", "web-3", "after"], order


class Wire(InProcessTransport):
    """The emulated drive's link, logging what each exchange was for ("status (web)" for the web
    process's reads); an exchange takes a few turns of the event loop, as one on a wire does."""

    def __init__(self, image: MotorRegisterImage) -> None:
        super().__init__(image)
        self.log: list[str] = []

    async def _exchange(self, what: str) -> None:
        self.log.append(what)
        for _ in range(3):
            await asyncio.sleep(0)

    async def read(self, address: int, count: int, what: str, function: int = 0x03) -> list[int]:
        await self._exchange(what)
        return await super().read(address, count, what, function)

    async def write(self, address: int, words: Sequence[int], what: str, *, retry: bool = True) -> None:
        await self._exchange(what)
        await super().write(address, words, what, retry=retry)


def _rig(body: object) -> Wire:
    profile = load_profile(None)
    clock = VirtualClock()
    model = MotorModel(profile.device, clock=clock.monotonic)
    wire = Wire(MotorRegisterImage(profile, model))

    async def go() -> None:
        motor = MotorController(profile, clock=clock)
        await motor.connect(OneAtATime(wire))
        rig = RigProcess(RIG_SPEC, motor)
        await body(rig)  # type: ignore[operator]
        await motor.close()

    asyncio.run(go())
    return wire


async def _web_reads(rig: RigProcess) -> list[asyncio.Task[list[int]]]:
    """The web process's forwarded status reads, queued on the link (the first one on the wire)."""
    reads = [asyncio.create_task(rig.transport.read(0, 1, WEB), name=f"web-{i}")
             for i in range(WEB_READS)]
    await asyncio.sleep(0)
    return reads


def test_the_watchdog_refresh_goes_before_the_web_process_s_queued_reads() -> None:
    async def body(rig: RigProcess) -> None:
        reads = await _web_reads(rig)
        keeper = asyncio.create_task(rig.keeper(), name="keeper")
        await asyncio.gather(*reads)
        keeper.cancel()
        await asyncio.gather(keeper, return_exceptions=True)

    log = _rig(body).log
    ours = [i for i, what in enumerate(log) if what != WEB]
    assert ours and ours[0] <= 1, log  # after at most the read already on the wire


def test_a_stop_goes_before_the_web_process_s_queued_reads() -> None:
    async def body(rig: RigProcess) -> None:
        reads = await _web_reads(rig)
        await asyncio.create_task(rig.stop("page", "stopped from the page"), name="stop")
        await asyncio.gather(*reads)

    log = _rig(body).log
    ours = [i for i, what in enumerate(log) if what != WEB]
    assert ours and ours[0] <= 1, log  # after at most the read already on the wire
    # each of the stop's exchanges (the quick stop, the read-back of standstill) waited for at most
    # the one read that took the link while the stop task was between two exchanges
    assert len(ours) >= 2 and all(b - a <= 2 for a, b in itertools.pairwise(ours)), log
    assert len(log) - len(ours) == WEB_READS
