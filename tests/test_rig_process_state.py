"""The rig process's state, in-process against the emulated drive on a virtual clock: what a stop's
answer says when the run it stops ends (and the web process says so) while the drive is read back,
and that the web process hears of the stop before the drive is commanded (its runs are aborted
before any answer can show them the drive's emergency-stop fault); a run refused while a stop is
held or its plan does not parse, and a run's progress told within its bounds."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import time

from drivers.motor import MotorController
from drivers.motor.profile import load_profile
from drivers.sim.clock import VirtualClock
from drivers.sim.motor_image import MotorRegisterImage
from drivers.sim.motor_model import MotorModel
from station.rigproc import channel
from station.rigproc.serve import RigProcess
from station.run.procedure import Progress
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


class Backlog:
    """The web process's socket as the rig process sees it: bytes told and not yet read."""

    def __init__(self) -> None:
        self.size = 0

    def get_write_buffer_size(self) -> int:
        return self.size


class ReadingWebEnd(WebEnd):
    """A web process that reads what it is told (or, ``transport.size`` set, has not read it)."""

    def __init__(self, model: MotorModel) -> None:
        super().__init__(model)
        self.transport = Backlog()
        self.told: list[dict[str, object]] = []

    def write(self, data: bytes) -> None:
        self.told.append(json.loads(data[4:]))


def test_a_run_is_refused_while_a_stop_is_held_or_its_plan_is_malformed_and_its_progress_is_bounded() -> None:
    replies: list[dict[str, object]] = []
    told: list[dict[str, object]] = []
    speeds: list[float] = []

    async def body(motor: MotorController, model: MotorModel, image: MotorRegisterImage, clock: VirtualClock) -> None:
        rig = RigProcess(SPEC, motor)
        web = ReadingWebEnd(model)
        rig.web = web  # type: ignore[assignment]
        start = {"op": "run_start", "run_id": "RUN-2", "config": {"not": "a configuration"}, "steps": [],
                 "out_dir": "/nonexistent", "hardware": {}, "radius_m": 0.001}
        replies.append(await rig.do(start))  # a plan that does not parse: refused, nothing started
        rig.hold("page", "stopped from the page")
        replies.append(await rig.do(start))  # a stop held: refused before the plan is read
        replies.append(await rig.do({"op": "run_abort", "run_id": "RUN-2", "reason": "x"}))  # no run: none aborted
        replies.append(await rig.do({"op": "run_outcome", "run_id": "RUN-2"}))
        speeds.append((await motor.read_status()).actual_speed_hz)
        # progress: a new step or state at once, within one at most every 0.25 s, none while unread
        p = Progress("RUN-3", state="running", step=0, n_steps=2, step_state="ramping")
        rig.runs.progress(p)
        rig.runs.progress(dataclasses.replace(p, samples=10))  # the same state, at once after: not told
        rig.runs.progress(dataclasses.replace(p, step_state="settling"))  # a new state: told
        web.transport.size = 10**6  # the web process reads nothing (stopped)
        time.sleep(0.3)
        rig.runs.progress(dataclasses.replace(p, step_state="settling", samples=20))  # dropped: unread
        rig.runs.progress(dataclasses.replace(p, step_state="recording"))  # a new state: told all the same
        told.extend(web.told)

    drive(load_profile(None), body)
    bad, held, aborted, outcome = replies
    assert bad["error"]["kind"] == "bad" and "configuration" in bad["error"]["detail"], bad  # type: ignore[index]
    assert held["error"]["kind"] == "refused" and "holds a stop" in held["error"]["detail"], held  # type: ignore[index]
    assert aborted == {"aborted": None} and outcome == {"running": False, "outcome": None}
    assert speeds == [0.0]
    assert [(m["event"], m["step_state"], m["samples"]) for m in told] == [
        ("run_progress", "ramping", 0), ("run_progress", "settling", 0), ("run_progress", "recording", 0)], told
    assert all(m["v"] == channel.VERSION == 4 for m in told)
