"""The calibration-run procedure: steps, settling, recording, and a safe stop on every path.

Per step: (stop and change the crank radius if the step asks for another) -> ramp to the crank
frequency -> settle -> wait until both signals are steady -> record -> next.  The motor watchdog is
refreshed throughout by the driver's keeper task.  An abort, a driver error, a motor fault or a
lost link first stops the motor (ramp down; emergency stop on a fault; if the link is gone the
controller's watchdog stops it), then closes the recording with the reason.

(About 400 lines, more than most modules: the run's sequence and every path that stops the motor
and closes the recording form one state machine; split up, the stop-on-every-path guarantee would
span files.)
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Protocol

from drivers.clock import Clock
from drivers.motor import MotorController, MotorStatus
from station.config import config_to_yaml
from station.environment import run_environment
from station.recording import ChannelSpec, RunMetadata, new_run_id
from station.recording.writer import DiskFullError, is_disk_full
from station.run.acquisition import AcquisitionError
from station.run.request import Plan, PlannedStep
from station.run.standstill import DriveCheck, read_back_standstill
from station.run.steady import SteadyCriteria
from station.run.stream import RecordingStream

log = logging.getLogger(__name__)


class RadiusActuator(Protocol):
    """Sets the crank radius (m) at standstill: motorised, simulated or fixed by hand."""

    radius_m: float

    async def set_radius(self, radius_m: float) -> None: ...


class FixedRadius:
    """A rig whose radius is set by hand: refuses to 'change' it to anything else."""

    def __init__(self, radius_m: float) -> None:
        self.radius_m = radius_m

    async def set_radius(self, radius_m: float) -> None:
        if not math.isclose(radius_m, self.radius_m, rel_tol=1e-9):
            raise RunFailure(f"this rig's crank radius is set by hand to {self.radius_m:g} m; "
                             f"the run asks for {radius_m:g} m")


class RunFailure(RuntimeError):
    """The run cannot go on; the message is the reason stored in the stop record."""


class RunAborted(RuntimeError):
    """An operator (or the emergency stop) aborted the run."""


StepState = Literal["", "ramping", "settling", "recording", "done", "stopping", "aborted", "failed", "interrupted"]
"""Where the step on the rig is (the last three: the run ended there)."""


@dataclass
class Progress:
    """Live state of a run for status displays."""

    run_id: str
    state: str = "starting"
    step: int | None = None
    n_steps: int = 0
    step_state: StepState = ""
    samples: int = 0
    lost_samples: int = 0
    message: str = ""

    @property
    def fraction(self) -> float:
        if not self.n_steps or self.step is None:
            return 0.0
        order = {"ramping": 0.1, "settling": 0.3, "recording": 0.6, "done": 1.0, "stopping": 1.0}
        if self.step_state not in order:  # stopped early (aborted, failed): the steps recorded before
            return min(1.0, self.step / self.n_steps)
        return min(1.0, (self.step + order[self.step_state]) / self.n_steps)


@dataclass(frozen=True)
class RunOutcome:
    run_id: str
    path: Path
    exit_status: str
    reason: str
    lost_samples: int


class RunProcedure(Protocol):
    """A run being carried out, as the daemon's run manager sees it: :class:`Procedure` in this
    process, or its remote form carrying the same run out in the rig process
    (``rigproc/remoterun.RemoteProcedure``); the same outcome either way."""

    run_id: str
    motor_fault: tuple[int, str] | None  # a controller fault seen at the start or during the run
    drive_check: DriveCheck | None  # the drive read back after the run's stop

    def abort(self, reason: str = "aborted by operator") -> None: ...

    async def execute(self) -> RunOutcome: ...


class RigDevices(Protocol):
    """What the procedure drives: the motor driver, the DAQ stream into the recording (in this
    process or under the rig process: ``stream.RecordingStream``) and a radius actuator, and the
    clock the rig keeps (real time; a virtual clock on the in-process simulated rig): every wait and
    time-out of the run is on it."""

    motor: MotorController
    daq: RecordingStream
    radius: RadiusActuator
    clock: Clock


def channel_specs(gain_V_per_m: float, lsb_d: float, lsb_f: float) -> tuple[ChannelSpec, ChannelSpec]:
    """Raw channel storage: ADC codes with their scaling to m (displacement) and V (force)."""
    return (ChannelSpec("displacement", "i2", "count", "m", scale=lsb_d / gain_V_per_m, volts_per_count=lsb_d),
            ChannelSpec("force", "i2", "count", "V", scale=lsb_f, volts_per_count=lsb_f))


class Procedure:
    """One calibration run on a connected rig.  ``await execute()`` returns the outcome; it never
    raises for run failures (they end in the stop record), only for programming errors."""

    def __init__(self, plan: Plan, rig: RigDevices, out_dir: str | Path, *, run_id: str | None = None,
                 on_progress: Callable[[Progress], None] | None = None,
                 steady: SteadyCriteria | None = None, reset_faults: bool = False,
                 on_disk_full: Callable[[], int] | None = None) -> None:
        self.plan = plan
        self.rig = rig
        self.clock = rig.clock
        self.out_dir = Path(out_dir)
        self.run_id = run_id or new_run_id(plan.config.transducer.id)
        self.progress = Progress(self.run_id, n_steps=len(plan.steps))
        self._on_progress = on_progress or (lambda p: None)
        self.steady = steady or SteadyCriteria()
        self.abort_event = asyncio.Event()
        self.abort_reason = ""
        self.acq: RecordingStream | None = None  # the DAQ stream once it streams for this run
        self.reset_faults = reset_faults  # an operator acknowledged a latched controller fault
        self.motor_fault: tuple[int, str] | None = None  # a controller fault seen at the start or during the run
        self.drive_check: DriveCheck | None = None  # the drive read back after the run's stop
        self._moving = False
        self.interrupted = False  # stopped by :meth:`interrupt`: it ends ``interrupted``
        self._on_disk_full = on_disk_full  # frees reserved space (bytes) so the recording can be closed

    def _release_reserve(self) -> int:
        if self._on_disk_full is None:
            return 0
        try:
            return self._on_disk_full()
        except Exception as exc:
            log.error("releasing the disk reserve failed: %s", exc)
            return 0

    def abort(self, reason: str = "aborted by operator") -> None:
        """Stop the run; the first reason given stays (a later abort does not overwrite it)."""
        if not self.abort_reason:
            self.abort_reason = reason
        self.abort_event.set()

    def interrupt(self, reason: str) -> None:
        """Stop the run as one the station's end cuts off: it ends ``interrupted`` (as a cancelled
        procedure does, without cancelling its own stop), unless it was aborted before."""
        if not self.abort_event.is_set():
            self.interrupted = True
        self.abort(reason)

    def _report(self, **kw: object) -> None:
        for k, v in kw.items():
            setattr(self.progress, k, v)
        if self.acq is not None:
            self.progress.samples = self.acq.samples
            self.progress.lost_samples = self.acq.lost_samples
        self._on_progress(self.progress)

    # ------------------------------------------------------------------------------ main
    async def execute(self) -> RunOutcome:
        cfg = self.plan.config
        motor, daq = self.rig.motor, self.rig.daq
        daq_cfg = await daq.configure(rate_hz=cfg.daq.sample_rate_hz, range_disp_V=cfg.daq.displacement_range_V,
                                      range_force_V=cfg.daq.force_range_V)
        # the quantisation step of the codes of the converter the bridge reports (connect refused a
        # configuration that disagrees with it); the configured resolution only for a bridge that reported none
        bits = daq.hardware.code_bits if daq.hardware is not None else cfg.daq.adc_bits
        lsb = 2.0 / 2**bits
        meta = RunMetadata(
            run_id=self.run_id, transducer_id=cfg.transducer.id, source="calibrate",
            sample_rate_hz=daq_cfg.rate_hz, load_mass_kg=cfg.rig.load_mass_kg,
            end_mass_kg=cfg.transducer.end_mass_kg,
            sensitivity_V_per_N=cfg.transducer.sensitivity_V_per_N * cfg.conditioner.gain,
            capacity_N=cfg.transducer.capacity_N, config_yaml=config_to_yaml(cfg),
            daq_hardware=None if daq.hardware is None else daq.hardware.as_attrs(),
            sample_rate_requested_hz=daq_cfg.rate_requested_hz,
            drive_profile_yaml=motor.profile.text or None, environment=run_environment(cfg))
        specs = channel_specs(cfg.displacement_sensor.gain_V_per_m, lsb * daq_cfg.range_disp_V,
                              lsb * daq_cfg.range_force_V)
        await daq.open(self.out_dir, meta, specs, plan=self.plan.to_dict(),
                       min_free_bytes=int(cfg.station.min_free_mb * 2**20))
        status, reason = "completed", ""
        error: BaseException | None = None
        try:
            dev = motor.profile.device
            beyond = [s.crank_frequency_hz for s in self.plan.steps
                      if not dev.min_frequency_hz <= s.crank_frequency_hz <= dev.max_frequency_hz]
            if beyond:
                raise RunFailure(f"crank frequencies {beyond} Hz: expected within what drive profile "
                                 f"{motor.profile.name!r} can be set to ({dev.min_frequency_hz:g}.."
                                 f"{dev.max_frequency_hz:g} Hz); nothing was moved")
            st = await self._wait_standstill()
            if st.fault_code and self.reset_faults:
                log.warning("run %s: controller fault %d (%s) reset as the operator asked", self.run_id,
                            st.fault_code, st.fault_name)
                await motor.reset_faults()
                st = await motor.read_status()
            if st.fault_code:  # never cleared behind the operator's back
                self.motor_fault = (st.fault_code, st.fault_name)
                raise RunFailure(f"the motor controller reports fault {st.fault_code} ({st.fault_name}) before "
                                 "the start; it is not cleared automatically: an operator acknowledges it "
                                 "(station daemon: POST /stop/acknowledge or `station ack`)")
            self._moving = True
            await motor.set_ramp(cfg.rig.acceleration_hz_per_s)
            await motor.ensure_watchdog()  # the drive's communication watchdog on, at the profile's time-out
            await motor.start_watchdog(0.2)
            await motor.enable()
            await daq.start()
            self.acq = daq
            self._report(state="running")
            for step in self.plan.steps:
                await self._step(step)
            self._report(step_state="stopping", message="all steps recorded; the crank ramps down to standstill")
            await self._ramp_to(0.0)
        except RunAborted as exc:
            status, reason = "interrupted" if self.interrupted else "aborted", str(exc)
        except asyncio.CancelledError:
            status, reason = "interrupted", "the station was stopped during the run"
        except (RunFailure, AcquisitionError) as exc:
            status, reason, error = "failed", str(exc), exc
        except Exception as exc:  # driver errors (lost link, Modbus exception, DAQ errors), a full disk
            status, reason, error = "failed", f"{type(exc).__name__}: {exc}", exc
        finally:
            if status != "completed":
                log.error("run %s %s: %s", self.run_id, status, reason)
                await self._stop_motor(hard=status == "failed" and self._moving)
            else:
                await self._quiet(motor.stop())
            await self._quiet(motor.stop_watchdog())
            end = await daq.stop()
            if status == "completed" and end.disk_error is not None:
                status, reason = "failed", f"recording cannot be written: {end.disk_error}"
            lost, disk_error = end.lost, end.disk_error
            if is_disk_full(error) or is_disk_full(disk_error):  # ENOSPC, not the writer's own reserve guard
                status, reason = "failed", ("recording cannot be written: disk full (no space left on device "
                                            f"in {self.out_dir})")
            disk_full = is_disk_full(error) or is_disk_full(disk_error) or isinstance(disk_error, DiskFullError)
            if disk_full:  # room to close the file and note the end: the daemon's reserve goes first
                self._release_reserve()
            try:
                path = await daq.finish(status, reason)
            except Exception as exc:  # e.g. a full disk: the partial file keeps what was flushed
                log.error("could not close the recording: %s", exc)
                path = daq.partial_path
                if is_disk_full(exc) and not disk_full and self._release_reserve():
                    try:
                        path = await daq.finish("failed", reason := f"{reason}; disk full while closing")
                    except Exception as exc2:
                        exc = exc2
                if path == daq.partial_path:
                    await daq.abandon()
                    reason = "; ".join(filter(None, [reason, f"recording left partial: {exc}"]))
            if daq.closed_as is not None:  # the stream closed it first (a lost web process): as the file says
                status, reason = daq.closed_as
            await self._verify_stopped(status)
            # a run that ended early is not "done": its progress stays at the steps it recorded
            self._report(state=status, message=reason, step_state="done" if status == "completed" else status)
        return RunOutcome(self.run_id, path, status, reason, lost)

    # ------------------------------------------------------------------------------ steps
    async def _step(self, step: PlannedStep) -> None:
        cfg = self.plan.config
        fs = cfg.daq.sample_rate_hz
        assert self.acq is not None
        if not math.isclose(step.crank_radius_m, self.rig.radius.radius_m, rel_tol=1e-9):
            self._report(step=step.index, step_state="ramping",
                         message=f"stopping to set the crank radius to {step.crank_radius_m:g} m")
            await self._ramp_to(0.0)
            await self.rig.radius.set_radius(step.crank_radius_m)
        self._report(step=step.index, step_state="ramping",
                     message=f"ramping to {step.crank_frequency_hz:g} Hz")
        await self._ramp_to(step.crank_frequency_hz)
        self._report(step_state="settling", message=f"settling {step.settle_s:g} s")
        await self._wait_samples(self.acq.samples + int(step.settle_s * fs))
        deadline = self.clock.monotonic() + self.steady.timeout_s
        while True:
            end = self.acq.samples
            if await self.acq.steady(step.crank_frequency_hz, fs, self.steady):
                break
            if self.clock.monotonic() > deadline:
                raise RunFailure(f"step {step.index} ({step.crank_frequency_hz:g} Hz): signals not steady "
                                 f"within {self.steady.timeout_s:g} s")
            await self._wait_samples(end + int(self.steady.window_s * fs))
        st = await self.rig.motor.read_status()
        start = self.acq.samples
        self._report(step_state="recording", message=f"recording {step.record_s:g} s")
        stop = start + round(step.record_s * fs)
        await self._wait_samples(stop)
        lost = await self.acq.lost_between(start, stop)
        if lost:
            log.warning("step %d: %d samples lost inside the record window", step.index, lost)
        await self.acq.add_step(crank_frequency_hz=step.crank_frequency_hz, crank_radius_m=step.crank_radius_m,
                                start_sample=start, end_sample=stop, lost_in_window=lost,
                                extra={"crank_angle_rad_at_start": st.crank_angle_rad,
                                       "actual_speed_hz_at_start": st.actual_speed_hz,
                                       "settle_s": step.settle_s, "record_s": step.record_s})
        self._report(step_state="done", message=f"step {step.index + 1} of {len(self.plan.steps)} recorded")

    async def _wait_standstill(self, timeout_s: float = 30.0) -> MotorStatus:
        """A run starts only with the crank at rest (e.g. still coasting down after an e-stop)."""
        deadline = self.clock.monotonic() + timeout_s
        while (st := await self.rig.motor.read_status()).actual_speed_hz != 0.0:
            if self.clock.monotonic() > deadline:
                raise RunFailure(f"the crank still turns at {st.actual_speed_hz:g} Hz after {timeout_s:g} s; "
                                 f"a run starts only at standstill")
            await self.clock.asleep(0.05)
        return st

    async def _ramp_to(self, hz: float) -> None:
        motor = self.rig.motor
        await motor.set_frequency(hz)
        st = await motor.read_status()
        acc = self.plan.config.rig.acceleration_hz_per_s
        deadline = self.clock.monotonic() + abs(st.actual_speed_hz - hz) / acc * 1.5 + 5.0
        while abs(st.actual_speed_hz - hz) > max(0.01, 1e-4 * hz):
            self._check()
            if self.clock.monotonic() > deadline:
                raise RunFailure(f"crank did not reach {hz:g} Hz (actual {st.actual_speed_hz:g} Hz)")
            await self.clock.asleep(0.05)
            st = await motor.read_status()
            self._check_motor(st)

    async def _wait_samples(self, sample: int) -> None:
        """Wait until ``sample`` samples are acquired, watching abort, acquisition and motor."""
        assert self.acq is not None
        fs = self.plan.config.daq.sample_rate_hz
        deadline = self.clock.monotonic() + (sample - self.acq.samples) / fs + 5.0
        next_status = 0.0
        while self.acq.samples < sample:
            self._check()
            now = self.clock.monotonic()
            if now > deadline:
                raise AcquisitionError(f"DAQ delivered {self.acq.samples} samples, {sample} awaited in time")
            if now >= next_status:
                self._check_motor(await self.rig.motor.read_status())
                next_status = now + 0.25
                self._report()
            await self.clock.asleep(0.02)

    def _check(self) -> None:
        if self.abort_event.is_set():
            raise RunAborted(self.abort_reason or "aborted")
        if self.acq is not None:
            self.acq.check()
        err = self.rig.motor.watchdog_error
        if err is not None:
            raise RunFailure(f"motor link lost (watchdog refresh failed): {err}")

    def _check_motor(self, st: MotorStatus) -> None:
        if self.abort_event.is_set():  # an operator's stop latches the e-stop fault: it is an abort
            raise RunAborted(self.abort_reason or "aborted")
        if st.fault_code:
            self.motor_fault = (st.fault_code, st.fault_name)
            raise RunFailure(f"motor fault {st.fault_code} ({st.fault_name})")

    async def _verify_stopped(self, status: str) -> None:
        """Read the drive back until it reports standstill (``drive_check``); a crank still turning
        gets the emergency stop as a last resort (the daemon latches it; the hardware stop is the
        operator's)."""
        if not self._moving:
            return
        motor = self.rig.motor
        ramp = min(self.plan.config.rig.acceleration_hz_per_s, motor.map.device.stop_deceleration_hz_per_s)
        bound = motor.stop_time_bound_s(motor.map.device.max_frequency_hz, ramp) + 2.0
        try:
            async with asyncio.timeout(bound):  # in this task (wait_for would run it in another one)
                self.drive_check = await read_back_standstill(
                    motor, f"the stop of run {self.run_id} ({status})", ramp)
        except TimeoutError:
            log.error("run %s: the drive did not answer its read-back within %.1f s", self.run_id, bound)
            return
        if self.drive_check.standstill is False:
            await self._quiet(motor.emergency_stop())

    async def _stop_motor(self, *, hard: bool) -> None:
        """Stop the crank before anything else: ramp down, or emergency stop on a failure."""
        motor = self.rig.motor
        if hard and await self._quiet(motor.emergency_stop()):
            return
        if not await self._quiet(motor.stop()):
            log.error("motor did not answer the stop; its watchdog stops it when refreshes cease")
            await self._quiet(motor.stop_watchdog())

    @staticmethod
    async def _quiet(aw: Awaitable[object]) -> bool:
        """Await ``aw``; log and swallow errors (used on the shutdown path). True on success."""
        try:
            async with asyncio.timeout(3.0):
                await aw
            return True
        except Exception as exc:
            log.warning("shutdown step failed: %s", exc)
            return False
