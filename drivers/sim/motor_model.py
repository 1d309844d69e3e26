"""Speed-ramp dynamics of the emulated crank motor controller (thread-safe, lazily integrated).

The model is exact for piecewise-constant acceleration: between two queries the speed moves
linearly towards its target at the ramp rate and the crank angle is the integral of the speed.
Time comes from an injectable clock (seconds, monotonic) so unit tests can step it.  The speed is
also known at past instants (:meth:`MotorModel.speed_hz` with ``at_s``, from the last minute's
ramps): the DAQ emulator synthesises each sample at the speed of its own instant, however late it
gets round to computing it.
"""

from __future__ import annotations

import bisect
import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from drivers.motor.profile import DeviceDefaults

log = logging.getLogger(__name__)

FAULT_NONE = 0
FAULT_WATCHDOG = 1
FAULT_ESTOP = 2
HISTORY_S = 60.0  # how far back the speed is known (s): far beyond any host stall


def _ramp_speed(v0: float, target: float, accel: float, dt: float) -> float:
    """Speed (Hz) ``dt`` s after ``v0`` when it moves towards ``target`` at ``accel`` Hz/s."""
    if accel <= 0.0 or v0 == target:
        return v0
    return v0 + math.copysign(min(accel * dt, abs(target - v0)), target - v0)


@dataclass(frozen=True)
class MotorSnapshot:
    """State at ``time_s``: speeds in Hz (rev/s), ramp in Hz/s, angle in rad (unwrapped)."""

    time_s: float
    enabled: bool
    setpoint_hz: float
    ramp_hz_per_s: float
    speed_hz: float
    angle_rad: float
    target_hz: float
    fault_code: int
    estop: bool
    watchdog_timeout_s: float
    watchdog_expired: bool


class MotorModel:
    """The shared motor state of the simulated rig (used by the Modbus server and the DAQ emulator)."""

    def __init__(self, device: DeviceDefaults, *, clock: Callable[[], float] = time.monotonic,
                 initial_angle_rad: float = 0.0) -> None:
        self.device = device
        self._clock = clock
        self._lock = threading.RLock()
        self._t = clock()
        self._enabled = False
        self._setpoint = 0.0
        self._ramp = device.default_ramp_hz_per_s
        self._speed = 0.0
        self._angle = initial_angle_rad
        self._fault = FAULT_NONE
        self._estop = False
        self._wd_timeout = device.default_watchdog_timeout_s
        self._wd_deadline = math.inf
        self.watchdog_refreshes = 0  # refreshes taken since the drive started
        self._wd_expired = False
        self._ignore_stops = False
        self._stuck_hz: float | None = None  # the speed a drive that ignores stops keeps turning at
        self._wd_required = True  # enabling with the watchdog off (time-out 0) is refused
        self._wd_active = True  # the watchdog stops the crank when it expires (a drive's detection and action)
        # the ramps so far: segment start times (s) and (speed at the start, target, accel) of each
        self._hist_t: list[float] = [self._t]
        self._hist: list[tuple[float, float, float]] = [(0.0, *self._target_and_accel())]

    # ----------------------------------------------------------------- dynamics
    def _target_and_accel(self) -> tuple[float, float]:
        if self._stuck_hz is not None:
            return self._stuck_hz, self._ramp
        if self._fault != FAULT_NONE:
            return 0.0, self.device.stop_deceleration_hz_per_s
        if not self._enabled:
            return 0.0, self._ramp
        return self._setpoint, self._ramp

    def _integrate(self, dt: float) -> None:
        target, accel = self._target_and_accel()
        v0 = self._speed
        if v0 == target or accel <= 0.0:
            self._angle += 2.0 * math.pi * v0 * dt
            return
        t_reach = abs(target - v0) / accel
        if t_reach >= dt:
            v1 = _ramp_speed(v0, target, accel, dt)
            self._angle += 2.0 * math.pi * 0.5 * (v0 + v1) * dt
            self._speed = v1
        else:
            self._angle += 2.0 * math.pi * (0.5 * (v0 + target) * t_reach + target * (dt - t_reach))
            self._speed = target

    def _advance(self) -> float:
        now = self._clock()
        while self._t < now:
            seg_end = now
            wd_armed = self._enabled and self._fault == FAULT_NONE and self._wd_timeout > 0 and self._wd_active
            if wd_armed and self._wd_deadline < now:
                seg_end = max(self._wd_deadline, self._t)
            self._record(now)
            self._integrate(seg_end - self._t)
            self._t = seg_end
            if wd_armed and seg_end < now:
                log.warning("motor emulator: watchdog expired (not refreshed for %.3f s): stopping",
                            self._wd_timeout)
                self._wd_expired = True
                self._latch_fault(FAULT_WATCHDOG)
        return now

    def _record(self, now: float) -> None:
        """Note the segment that starts at ``self._t`` if its target or ramp differs from the last."""
        target, accel = self._target_and_accel()
        _, last_target, last_accel = self._hist[-1]
        if (target, accel) != (last_target, last_accel):
            self._hist_t.append(self._t)
            self._hist.append((self._speed, target, accel))
        if len(self._hist_t) > 64 and self._hist_t[32] < now - HISTORY_S:
            del self._hist_t[:32], self._hist[:32]

    def _stopping(self) -> None:
        """A command that would slow the crank down: a drive that ignores stops keeps its target."""
        if self._ignore_stops and self._stuck_hz is None:
            self._stuck_hz = self._target_and_accel()[0]

    def _latch_fault(self, code: int) -> None:
        self._stopping()
        if self._fault == FAULT_NONE:
            self._fault = code
        self._enabled = False

    # ----------------------------------------------------------------- queries
    def snapshot(self) -> MotorSnapshot:
        """Advance to now and return the state."""
        with self._lock:
            now = self._advance()
            target, _ = self._target_and_accel()
            return MotorSnapshot(now, self._enabled, self._setpoint, self._ramp, self._speed, self._angle,
                                 target, self._fault, self._estop, self._wd_timeout, self._wd_expired)

    def speed_hz(self, at_s: float | None = None) -> float:
        """Actual crank frequency in Hz now, or at the clock time ``at_s`` (s) of the last minute
        (a time after now counts as now: the future is not known yet)."""
        with self._lock:
            now = self._advance()
            if at_s is None or at_s >= now:
                return self._speed
            i = max(0, bisect.bisect_right(self._hist_t, at_s) - 1)
            v0, target, accel = self._hist[i]
            return _ramp_speed(v0, target, accel, max(0.0, at_s - self._hist_t[i]))

    # ----------------------------------------------------------------- commands
    @contextlib.contextmanager
    def atomic(self) -> Iterator[None]:
        """All commands inside happen together or not at all (a multi-register write): on an
        exception the state is restored, as if nothing had been commanded."""
        with self._lock:
            saved = {k: v for k, v in vars(self).items() if k.startswith("_") and k not in ("_lock", "_clock")}
            try:
                yield
            except BaseException:
                vars(self).update(saved)
                # the history lists are shared with the saved state: forget the segments begun since
                keep = bisect.bisect_left(self._hist_t, self._t)
                del self._hist_t[max(1, keep):], self._hist[max(1, keep):]
                raise

    def set_enable(self, on: bool) -> None:
        """Enable/disable; enabling with a latched fault or with the watchdog off (timeout 0) raises
        ``PermissionError``."""
        with self._lock:
            now = self._advance()
            if on and self._fault != FAULT_NONE:
                raise PermissionError(f"fault {self._fault} latched: reset it first")
            if on and self._wd_timeout <= 0 and self._wd_required:
                raise PermissionError("the watchdog is off (timeout 0): set a timeout before enabling")
            if on and not self._enabled:
                self._wd_deadline = now + self._wd_timeout
                self._wd_expired = False
            if not on:
                self._stopping()
            self._enabled = on

    def set_setpoint(self, hz: float) -> None:
        """Crank frequency setpoint in Hz; beyond [min, max] raises ``ValueError``."""
        with self._lock:
            self._advance()
            if not self.device.min_frequency_hz <= hz <= self.device.max_frequency_hz:
                raise ValueError(f"setpoint {hz} Hz outside [{self.device.min_frequency_hz}, "
                                 f"{self.device.max_frequency_hz}] Hz")
            if hz < self._setpoint:
                self._stopping()
            self._setpoint = hz

    def set_ramp(self, hz_per_s: float) -> None:
        """Acceleration ramp in Hz/s; must be in (0, max_ramp] else ``ValueError``."""
        with self._lock:
            self._advance()
            if not 0.0 < hz_per_s <= self.device.max_ramp_hz_per_s:
                raise ValueError(f"ramp {hz_per_s} Hz/s outside (0, {self.device.max_ramp_hz_per_s}] Hz/s")
            self._ramp = hz_per_s

    def refresh_watchdog(self) -> None:
        with self._lock:
            now = self._advance()
            self._wd_deadline = now + self._wd_timeout
            self.watchdog_refreshes += 1


    def play_drive_defaults(self, watchdog_timeout_s: float) -> None:
        """Behave as a drive out of the box: its communication time-out as the factory set it (0: off)
        and, unlike the station's own controller, enabling even while the watchdog is off."""
        with self._lock:
            now = self._advance()
            self._wd_required = False
            self._wd_timeout = watchdog_timeout_s
            self._wd_deadline = now + watchdog_timeout_s

    def set_watchdog_active(self, on: bool) -> None:
        """Whether an expired watchdog stops the crank (a drive's communication-loss detection and its
        action both set to stop); off, the drive keeps turning when the link is lost."""
        with self._lock:
            now = self._advance()
            if on and not self._wd_active:
                self._wd_deadline = now + self._wd_timeout
            self._wd_active = on

    def set_watchdog_timeout(self, seconds: float) -> None:
        """0 disables the watchdog: refused (``PermissionError``) while the drive is enabled."""
        with self._lock:
            now = self._advance()
            if seconds < 0:
                raise ValueError(f"watchdog timeout must be >= 0 s, got {seconds}")
            if seconds == 0 and self._enabled:
                raise PermissionError("the watchdog cannot be switched off while the drive is enabled")
            self._wd_timeout = seconds
            self._wd_deadline = now + seconds

    def emergency_stop(self) -> None:
        with self._lock:
            self._advance()
            self._estop = True
            self._latch_fault(FAULT_ESTOP)

    def inject_fault(self, code: int) -> None:
        """Fault injection: latch ``code`` (non-zero) as if the drive had detected it."""
        if code == FAULT_NONE:
            raise ValueError("inject a non-zero fault code")
        with self._lock:
            self._advance()
            self._latch_fault(code)

    def ignore_stops(self, on: bool = True) -> None:
        """Fault injection: the drive takes every command (no Modbus exception) but keeps turning
        when told to stop or slow down (emergency stop, disable, a lower setpoint, its own watchdog
        or a fault): a broken power stage or a welded contactor.  ``ignore_stops(False)`` repairs it;
        the drive then obeys its latched state (a fault latched meanwhile stops it at the stop ramp)."""
        with self._lock:
            self._advance()
            self._ignore_stops = on
            if not on:
                self._stuck_hz = None

    def preset_angle(self, angle_rad: float) -> None:
        """Test hook: set the unwrapped crank angle (rad), as if the crank had turned that far."""
        with self._lock:
            self._advance()
            self._angle = angle_rad

    def reset_faults(self) -> None:
        """Clear latched faults; refused (``PermissionError``) while the crank still turns."""
        with self._lock:
            self._advance()
            if self._speed != 0.0:
                raise PermissionError(f"cannot reset faults while turning at {self._speed:.2f} Hz")
            self._fault = FAULT_NONE
            self._estop = False
            self._wd_expired = False
