"""The rig process's state, in-process against the emulated drive on a virtual clock: what a stop's
answer says when the run it stops ends (and the web process says so) while the drive is read back,
and that the web process hears of the stop before the drive is commanded (its runs are aborted
before any answer can show them the drive's emergency-stop fault)."""

from __future__ import annotations

import asyncio
import json

from drivers.motor import MotorController
from drivers.motor.profile import load_profile
from drivers.sim.clock import VirtualClock
from drivers.sim.motor_image import MotorRegisterImage
from drivers.sim.motor_model import MotorModel
from station.rigproc import channel
from station.rigproc.serve import RigProcess
from tests.drive_support import RIG_SPEC as SPEC
from tests.drive_support import drive


class WebEnd:
    """The web process's end of the channel: the events told, each with the drive's state then."""

    def __init__(self, model: MotorModel) -> None:
        self.model = model
        self.events: list[tuple[str, bool]] = []  # (event, the drive in its emergency stop when told)

    def is_closing(self) -> bool:
        return False

    def write(self, data: bytes) -> None:
        msg = json.loads(data[4:])
        assert int.from_bytes(data[:4], "big") == len(data) - 4 and msg["v"] == channel.VERSION
        self.events.append((msg["event"], self.model.snapshot().estop))


def test_a_stop_names_the_run_the_crank_turned_for_when_it_was_given() -> None:
    answers: list[dict[str, object]] = []
    speeds: list[float] = []
    told: list[tuple[str, bool]] = []

    async def body(motor: MotorController, model: MotorModel, image: MotorRegisterImage, clock: VirtualClock) -> None:
        rig = RigProcess(SPEC, motor)
        web = WebEnd(model)
        rig.web = web  # type: ignore[assignment]
        await motor.enable()
        await motor.set_frequency(10.0)
        await motor.wait_for_speed(10.0, timeout_s=30.0)
        speeds.append((await motor.read_status()).actual_speed_hz)
        await rig.do({"op": "run", "run_id": "RUN-1"})
        stopping = asyncio.create_task(rig.stop("page", "stopped from the page"))
        while rig.latched is None:  # the stop is given; the drive is still being stopped and read back
            await asyncio.sleep(0)
        assert not stopping.done()
        await rig.do({"op": "run", "run_id": None})  # the run saw the fault and ended meanwhile
        answers.append(await stopping)
        answers.append(await rig.stop("page", "a second stop, with no run"))
        told.extend(web.events)

    drive(load_profile(None), body)
    assert speeds[0] > 9.0  # the crank turned when the stop was given
    first, second = answers
    assert first["aborted_runs"] == ["RUN-1"] and first["motor_stopped"], first
    assert second["aborted_runs"] == [], second
    # told before the drive was commanded; the stop given, after
    assert told == [("stopping", False), ("stopped", True), ("stopping", True), ("stopped", True)], told
