"""The crank drive's driver: one interface for every drive profile, the backend (transport) chosen at
connect time.

Usage (asyncio)::

    motor = MotorController(load_profile("toshiba-vf-s11"))  # default: the station's own controller
    await motor.connect(ModbusTransport.tcp("127.0.0.1", 5020))
    await motor.set_ramp(5.0); await motor.enable(); await motor.set_frequency(20.0)
    status = await motor.read_status()                     # MotorStatus
    ...
    await motor.stop(); await motor.close()

The station must refresh the drive's watchdog: call :meth:`refresh_watchdog` at least every
watchdog time-out (or run :meth:`start_watchdog`); otherwise the drive stops the motor.  Commands
(enable, stop, quick stop, fault reset) are the profile's write sequences with their hold times.
Before the first enable of a connection the profile's safety settings (communication-loss stop, command
source, stop method, the frequency the scaling rests on) are armed and read back (:meth:`arm`); a drive
that does not hold them is not enabled (:class:`MotorSafetyError` naming the parameter).  A command word
is sent once: only the registers the profile lists in ``transport.retry_writes`` are sent again after a
time-out.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass

from drivers.clock import REAL_CLOCK, Clock
from drivers.motor.errors import (
    MotorCommunicationError,
    MotorError,
    MotorExceptionReplyError,
    MotorFaultError,
    MotorSafetyError,
    MotorStateError,
    MotorValueError,
)
from drivers.motor.profile import PSEUDO_ESTOP, PSEUDO_FAULT, CommandStep, DriveProfile, load_profile
from drivers.motor.transport import PeerKeptWatchdog, RegisterTransport

log = logging.getLogger(__name__)

# writes of one EEPROM-backed register per connection beyond which the driver refuses: an EEPROM lasts
# 10^4..10^5 writes, so such a register is written when its value changes, never in a loop
EEPROM_WRITES_PER_CONNECTION = 4


@dataclass(frozen=True)
class MotorStatus:
    """One consistent read of the drive's status.

    actual_speed_hz: crank frequency in Hz (rev/s); crank_angle_rad in [0, 2*pi) (None: the drive has
    no angle register); flags: the canonical flags (ready, enabled, running, at_setpoint, fault, estop)
    and the profile's own; fault_code 0 = none (``PSEUDO_ESTOP``/``PSEUDO_FAULT`` when the drive shows
    a quick stop or a fault without a code); time_s: the driver's clock (``time.monotonic()`` on a
    real rig) at the middle of the request (the angle's timestamp, to within half ``round_trip_s``).
    """

    actual_speed_hz: float
    crank_angle_rad: float | None
    status_word: int
    flags: Mapping[str, bool]
    fault_code: int
    fault_name: str
    revolution_count: int | None
    time_s: float
    round_trip_s: float

    @property
    def crank_angle_deg(self) -> float | None:
        return None if self.crank_angle_rad is None else math.degrees(self.crank_angle_rad)

    @property
    def standstill(self) -> bool:
        """The crank does not turn (speed 0, flag ``running`` clear)."""
        return self.actual_speed_hz == 0.0 and not self.flags.get("running", False)

    @property
    def estop_latched(self) -> bool:
        return bool(self.flags.get("estop", False))

    def describe(self) -> str:
        """One line for logs and error messages, e.g. ``standstill, disabled, fault 2 (emergency_stop)``."""
        parts = ["standstill" if self.standstill else f"turning at {self.actual_speed_hz:g} Hz",
                 "enabled" if self.flags.get("enabled") else "disabled",
                 f"fault {self.fault_code} ({self.fault_name})" if self.fault_code else "no fault"]
        if self.estop_latched:
            parts.append("emergency stop latched")
        return ", ".join(parts)


class MotorController:
    """Driver of a crank drive described by a :class:`DriveProfile`, over any :class:`RegisterTransport`."""

    def __init__(self, profile: DriveProfile | None = None, *, clock: Clock = REAL_CLOCK) -> None:
        """``profile``: the drive (default: the station's own controller, ``sinecal-crank``);
        ``clock``: time of the status stamps, the command hold times, the watchdog keeper and
        ``wait_for_speed`` (real time, or the virtual clock of an in-process simulated rig)."""
        self.profile = profile or load_profile()
        self.map = self.profile  # registers by name: ``motor.map["frequency_setpoint"]``
        self.clock = clock
        self._t: RegisterTransport | None = None
        self._wd_counter = 0
        self._wd_task: asyncio.Task[None] | None = None
        self._setpoint_hz = 0.0
        self.watchdog_error: MotorError | None = None
        self.eeprom_writes: Counter[str] = Counter()
        self.armed: dict[str, float] = {}  # parameter -> value read back by arm() (empty: not armed)
        self._armed = False
        self._ramp_reference_hz: float | None = None  # the drive's maximum frequency, read back
        self._last_words: dict[str, list[int]] = {}  # the last words written to each register
        # a command sequence, a set point and a watchdog rewrite never interleave (the emergency stop
        # takes no lock: it never waits for anything)
        self._io = asyncio.Lock()
        self._watchdog_set_s: float | None = None  # the time-out set_watchdog_timeout() last set

    @property
    def transport(self) -> RegisterTransport:
        if self._t is None:
            raise MotorError("motor controller not connected: call connect(transport) first")
        return self._t

    async def connect(self, transport: RegisterTransport) -> None:
        """Attach the backend (Modbus TCP/RTU or in-process) and open it."""
        await transport.open()
        self._t = transport
        self.eeprom_writes.clear()
        self.armed, self._armed, self._ramp_reference_hz = {}, False, None
        self._watchdog_set_s = None
        self._last_words.clear()
        log.info("motor controller (%s) connected via %s", self.profile.name, transport.description)

    async def close(self) -> None:
        await self.stop_watchdog()
        if self._t is not None:
            await self._t.close()
            self._t = None

    # --------------------------------------------------------------- register level
    async def read(self, name: str) -> float:
        """Physical value of one register, in its unit (see the profile)."""
        reg = self.profile[name]
        return reg.decode(await self.transport.read(reg.address, reg.words, name, reg.read_function))

    async def write(self, name: str, value: float) -> None:
        """Write one register (physical value in its unit).

        A value outside the register's declared range (the profile's ``min``/``max``) is refused
        here, before anything is sent (:class:`MotorValueError`), and so is a write to an EEPROM-backed
        register beyond ``EEPROM_WRITES_PER_CONNECTION`` per connection."""
        reg = self.profile[name]
        if not reg.writable:
            raise MotorValueError(f"register {name!r} is read-only")
        reg.check(value)
        await self._write_words(name, reg.encode(value))

    async def _write_words(self, name: str, words: list[int]) -> None:
        reg = self.profile[name]
        if reg.eeprom:
            if self.eeprom_writes[name] >= EEPROM_WRITES_PER_CONNECTION:
                raise MotorValueError(
                    f"register {name!r} is EEPROM-backed and was written {self.eeprom_writes[name]} times "
                    "since connect: refused (an EEPROM wears out; it is written when its value changes, "
                    "never in a loop)")
            self.eeprom_writes[name] += 1
        self._last_words[name] = list(words)
        retry = name in self.profile.transport.retry_writes
        await self.transport.write(reg.address, words, name, retry=retry)

    async def set_parameter(self, name: str, value: float) -> bool:
        """Set a parameter: an EEPROM-backed one is read first and written only if it differs (to its
        resolution), a RAM one is written.  Returns whether it wrote."""
        reg = self.profile[name]
        reg.check(value)
        if reg.eeprom and reg.raw_of(await self.read(name)) == reg.raw_of(value):
            return False
        await self.write(name, value)
        return True

    async def _run(self, *commands: str, lock: bool = True) -> None:
        """Carry out commands of the profile's command model in turn, step by step with their hold times
        (each word sent once), then read back the steps marked ``verify``.  ``lock=False`` (the
        emergency stop): without waiting for a set point or a watchdog refresh under way."""
        if lock:
            async with self._io:
                await self._steps(commands)
        else:
            await self._steps(commands)

    async def _steps(self, commands: tuple[str, ...]) -> None:
        seqs = self.profile.commands.sequences
        steps: list[CommandStep] = [step for c in commands if c in seqs for step in seqs[c]]
        for i, step in enumerate(steps):
            reg = self.profile[step.register]
            await self._write_words(step.register, reg.words_of_raw(step.value))
            if step.register == self.profile.setpoint:
                self._setpoint_hz = reg.decode(reg.words_of_raw(step.value))
            if step.hold_s > 0 and i < len(steps) - 1:
                await self.clock.asleep(step.hold_s)
        for step in steps:
            if step.verify:
                reg = self.profile[step.register]
                raw = reg.decode_raw(await self.transport.read(reg.address, reg.words, f"{reg.name} (read back)",
                                                               reg.read_function))
                if raw != step.value:
                    raise MotorStateError(f"register {reg.name!r}: wrote {step.value}, read back {raw} "
                                          f"(drive profile {self.profile.name!r}): the drive did not take it")

    # --------------------------------------------------------------- safety settings
    async def arm(self) -> dict[str, float]:
        """Arm the drive's safety settings and read each back: the profile's ``safety`` list (a ``set``
        setting is written when the drive holds another value, once; a ``check`` setting is only
        read) and the communication watchdog's time-out.  Returns {parameter: value read back}.

        Raises :class:`MotorSafetyError` naming the first parameter that does not hold its required
        value; until then the drive is not enabled (:meth:`enable` arms first)."""
        p = self.profile
        self._armed = False
        found: dict[str, float] = {}
        for s in p.safety:
            reg = p[s.register]
            value = await self.read(s.register)
            if s.how == "set" and not s.holds(value, reg.scale):
                assert s.value is not None
                log.warning("drive %s: %s is %g, setting it to %s", p.name, s.parameter, value, s.required())
                await self.write(s.register, s.value)
                value = await self.read(s.register)
                if not s.holds(value, reg.scale):
                    raise MotorSafetyError(p.name, s.parameter, s.register, s.required(),
                                           f"wrote {s.value:g}, read back {value:g}",
                                           "the drive does not keep it (parameter lock? set it on its panel)")
            if not s.holds(value, reg.scale):
                raise MotorSafetyError(p.name, s.parameter, s.register, s.required(), f"read back {value:g}",
                                       "set it on the drive's panel (the station only checks it)")
            found[s.parameter] = value
        wd = p.watchdog
        want = self._watchdog_set_s  # a time-out the caller chose on this connection, else the profile's
        if not want:
            await self.ensure_watchdog()
            want = wd.timeout_s
        value = await self.read(wd.register)
        name = wd.parameter or wd.register
        if abs(value - want) > 0.5 * abs(p[wd.register].scale):
            raise MotorSafetyError(p.name, name, wd.register, f"{want:g} s (the communication time-out)",
                                   f"read back {value:g} s", "the drive does not keep it")
        found[name] = value
        self.armed, self._armed = found, True
        log.info("drive %s armed: %s", p.name, ", ".join(f"{k} = {v:g}" for k, v in found.items()))
        return found

    async def _ramp_reference(self) -> float:
        """The frequency a ramp time runs to (Hz): the drive's maximum frequency read back where the
        profile has its register (the VF-S11's FH), else the set point's maximum."""
        p = self.profile
        if p.max_frequency is None:
            return p.device.max_frequency_hz
        if self._ramp_reference_hz is None:
            fh = await self.read(p.max_frequency)
            if not fh > 0:
                raise MotorSafetyError(p.name, p.max_frequency, p.max_frequency, "> 0 Hz", f"read back {fh:g}",
                                       "the ramp times cannot be scaled")
            self._ramp_reference_hz = fh
        return self._ramp_reference_hz
    # --------------------------------------------------------------- commands
    async def enable(self) -> None:
        """Enable the drive: it follows the set point (the watchdog starts counting).  The profile's
        ``enable`` sequence, then its ``run`` sequence where it has one; the safety settings are armed
        and read back first, once per connection (:meth:`arm`, :class:`MotorSafetyError`)."""
        if not self._armed:
            await self.arm()
        await self._run("enable", "run")

    async def disable(self) -> None:
        """Ramp down to standstill and disable (the profile's ``stop`` sequence)."""
        await self._run("stop")

    async def set_frequency(self, hz: float) -> None:
        """Crank-frequency set point in Hz; checked against the register's range before sending."""
        async with self._io:
            await self.write(self.profile.setpoint, hz)
            self._setpoint_hz = hz

    async def set_ramp(self, hz_per_s: float) -> None:
        """Acceleration ramp in Hz/s (magnitude), within the drive's range (min <= ramp <= max, > 0).  A ramp
        parameter is written only when it changes (it may live in EEPROM)."""
        ramp = self.profile.ramp
        if ramp is None:
            log.info("profile %s has no ramp parameter: the drive keeps its own ramp", self.profile.name)
            return
        dev = self.profile.device
        if not (hz_per_s > 0 and dev.min_ramp_hz_per_s <= hz_per_s <= dev.max_ramp_hz_per_s):
            raise MotorValueError(f"ramp: expected {dev.min_ramp_hz_per_s:g}..{dev.max_ramp_hz_per_s:g} Hz/s "
                                  f"(drive profile {self.profile.name!r}), got {hz_per_s!r} Hz/s")
        value = hz_per_s if ramp.form == "rate" else await self._ramp_reference() / hz_per_s
        for name in ramp.registers:
            await self.set_parameter(name, value)

    async def set_watchdog_timeout(self, seconds: float) -> None:
        """Watchdog time-out in s; 0 (off) is refused while the drive is enabled (checked here first,
        :class:`MotorStateError`; the emulated controller refuses it too, exception 04)."""
        name = self.profile.watchdog.register
        self.profile[name].check(seconds)
        if 0 < seconds < self.profile.watchdog.min_s:
            raise MotorValueError(f"register {name!r}: expected 0 (off) or at least the drive's smallest time-out "
                                  f"{self.profile.watchdog.min_s:g} s, got {seconds!r} s")
        if seconds == 0 and (await self.read_status()).flags.get("enabled"):
            raise MotorStateError("watchdog_timeout: expected a timeout > 0 s while the drive is enabled, "
                                  "got 0 (the watchdog cannot be switched off while enabled)")
        await self.set_parameter(name, seconds)
        self._watchdog_set_s = seconds

    async def ensure_watchdog(self) -> None:
        """Set the drive's communication watchdog to the profile's time-out (written only if it differs)."""
        await self.set_watchdog_timeout(self.profile.watchdog.timeout_s)

    async def refresh_watchdog(self) -> None:
        """Refresh the drive's watchdog the way the drive counts it: write the next rolling counter
        value to its refresh register; rewrite the last value of a process-data register (a drive
        that counts only received set points or command words); or, where every valid request
        refreshes it, read the status word."""
        wd = self.profile.watchdog
        refresh = wd.refresh
        if wd.rewrite is not None:
            reg = self.profile[wd.rewrite]
            async with self._io:
                words = self._last_words.get(reg.name)
                if words is None:
                    words = await self.transport.read(reg.address, reg.words, f"{reg.name} (watchdog refresh)",
                                                      reg.read_function)
                await self.transport.write(reg.address, words, f"{reg.name} (watchdog refresh)",
                                           retry=reg.name in self.profile.transport.retry_writes)
                self._last_words[reg.name] = list(words)
            return
        if refresh is None:
            reg = self.profile[self.profile.status.register]
            await self.transport.read(reg.address, reg.words, f"{reg.name} (watchdog refresh)", reg.read_function)
            return
        self._wd_counter = (self._wd_counter + 1) & 0xFFFF
        await self.write(refresh, self._wd_counter)

    async def stop(self) -> None:
        """Normal stop: set point 0, then the ``stop`` sequence; the drive ramps down at its ramp."""
        await self.set_frequency(0.0)
        await self.disable()

    async def emergency_stop(self) -> None:
        """Emergency (quick) stop: latched; the drive decelerates at its stop ramp.  Clear with reset_faults.

        Waits for nothing under way.  A drive that must not be told twice (``repeat_quick_stop: false``:
        the VF-S11 reboots) is read first and not told again while its quick stop is latched."""
        if not self.profile.commands.repeat_quick_stop:
            try:
                st = await self.read_status()
            except MotorError as exc:
                log.warning("status before the quick stop unreadable (%s): sending it", exc)
            else:
                if st.estop_latched:
                    log.info("drive %s: quick stop already latched, not sent again", self.profile.name)
                    return
        await self._run("quick_stop", lock=False)

    async def reset_faults(self) -> None:
        """Clear latched faults (the drive refuses while the crank still turns).

        A drive whose reset reboots it (``commands.reset_reboot_s``, the VF-S11) is sent the reset once
        (no reply is expected), left to reboot, read until it answers again (within another reboot
        time), then given back the set point and the stopped command word its reboot cleared."""
        reboot = self.profile.commands.reset_reboot_s
        if reboot <= 0:
            await self._run("fault_reset")
            return
        try:
            await self._run("fault_reset")
        except MotorExceptionReplyError:
            raise  # refused (e.g. the crank still turns): no reboot
        except MotorCommunicationError as exc:
            log.info("drive %s: no reply to the fault reset, as when it reboots (%s)", self.profile.name, exc)
        await self.clock.asleep(reboot)
        deadline = self.clock.monotonic() + reboot
        while True:
            try:
                await self.read_status()
                break
            except MotorCommunicationError:
                if self.clock.monotonic() > deadline:
                    raise
                await self.clock.asleep(0.2)
        async with self._io:
            await self.write(self.profile.setpoint, self._setpoint_hz)
        await self._run("stop")

    async def read_status(self) -> MotorStatus:
        """Read speed, status, fault code (and angle, revolutions where the drive has them), each
        contiguous run of registers in one request (within the drive's longest read)."""
        p = self.profile
        names = [n for n in (p.speed, p.status.register, p.faults.register, p.angle, p.revolutions) if n]
        values: dict[str, list[int]] = {}
        t0 = self.clock.monotonic()
        for fc, start, count, members in p.blocks(names):
            words = await self.transport.read(start, count, "status block (" + ", ".join(members) + ")", fc)
            for n in members:
                reg = p[n]
                values[n] = words[reg.address - start: reg.address - start + reg.words]
        t1 = self.clock.monotonic()

        def get(name: str) -> float:
            return p[name].decode(values[name])

        speed = get(p.speed)
        word = int(p[p.status.register].decode_raw(values[p.status.register])) & 0xFFFF
        flags = p.decode_status(word)
        code = int(get(p.faults.register)) if p.faults.register else 0
        flags.setdefault("running", speed != 0.0)
        flags.setdefault("fault", code != 0)
        flags.setdefault("estop", code != 0 and code == p.faults.kinds.get("emergency_stop"))
        resolution = abs(p[p.setpoint].scale)
        flags.setdefault("at_setpoint", flags["enabled"] and abs(speed - self._setpoint_hz) <= 0.5 * resolution)
        flags.setdefault("ready", not flags["fault"] and not flags["enabled"])
        if code == 0 and flags["estop"]:
            code = PSEUDO_ESTOP
        elif code == 0 and flags["fault"]:
            code = PSEUDO_FAULT
        angle: float | None = None
        if p.angle:
            a = get(p.angle)
            angle = (math.radians(a) if p[p.angle].unit == "deg" else a) % (2 * math.pi)
        return MotorStatus(
            actual_speed_hz=speed,
            crank_angle_rad=angle,
            status_word=word,
            flags=flags,
            fault_code=code,
            fault_name=p.fault_name(code),
            revolution_count=int(get(p.revolutions)) if p.revolutions else None,
            time_s=0.5 * (t0 + t1),
            round_trip_s=t1 - t0,
        )

    async def read_state(self) -> MotorStatus:
        """The controller's state as it is (standstill, enable, fault code, e-stop latch), logged.

        Reports only: nothing is written, a latched fault stays latched (clearing it is the
        operator's decision, :meth:`reset_faults`)."""
        st = await self.read_status()
        level = logging.WARNING if (st.fault_code or not st.standstill) else logging.INFO
        log.log(level, "motor controller state: %s", st.describe())
        return st

    async def check_standstill(self) -> MotorStatus:
        """Require a known, safe state before a run: standstill, disabled and no latched fault.

        Raises :class:`MotorFaultError` (fault latched, not cleared) or :class:`MotorStateError`
        (turning or enabled), each naming what was expected and what was found."""
        st = await self.read_state()
        if st.fault_code != 0:
            raise MotorFaultError(st.fault_code, st.fault_name)
        if not st.standstill or st.flags.get("enabled"):
            raise MotorStateError(f"motor controller: expected standstill and disabled, found {st.describe()}")
        return st

    async def require_no_fault(self) -> MotorStatus:
        """Read the status; raise :class:`MotorFaultError` if the controller has a latched fault."""
        st = await self.read_status()
        if st.fault_code != 0:
            raise MotorFaultError(st.fault_code, st.fault_name)
        return st

    async def settle_to_standstill(self, timeout_s: float, *, poll_s: float = 0.05) -> MotorStatus:
        """Read the status until the drive reports standstill or ``timeout_s`` (s, on the driver's
        clock) has passed; returns the last status read (``standstill`` says which).  Never raises
        for a crank still turning: that is the caller's finding; link errors propagate."""
        deadline = self.clock.monotonic() + timeout_s
        st = await self.read_status()
        while not st.standstill and self.clock.monotonic() < deadline:
            await self.clock.asleep(poll_s)
            st = await self.read_status()
        return st

    def stop_time_bound_s(self, speed_hz: float, ramp_hz_per_s: float | None = None) -> float:
        """How long (s) a healthy drive may take to come to rest from ``speed_hz``: the ramp
        (default: the controller's documented stop deceleration) with 50 % margin, plus 1 s."""
        ramp = ramp_hz_per_s or self.map.device.stop_deceleration_hz_per_s
        return abs(speed_hz) / ramp * 1.5 + 1.0

    async def wait_for_speed(self, hz: float, *, tolerance_hz: float = 0.01, timeout_s: float = 30.0,
                             poll_s: float = 0.05, keep_watchdog: bool = True) -> MotorStatus:
        """Poll until |actual - hz| <= tolerance, refreshing the watchdog; TimeoutError otherwise."""
        deadline = self.clock.monotonic() + timeout_s
        while True:
            if keep_watchdog:
                await self.refresh_watchdog()
            st = await self.read_status()
            if abs(st.actual_speed_hz - hz) <= tolerance_hz:
                return st
            if self.clock.monotonic() > deadline:
                raise TimeoutError(f"crank did not reach {hz} Hz within {timeout_s} s "
                                   f"(actual {st.actual_speed_hz} Hz, fault {st.fault_name})")
            await self.clock.asleep(poll_s)

    # --------------------------------------------------------------- watchdog keeper
    async def start_watchdog(self, period_s: float = 0.2) -> None:
        """Refresh the watchdog every ``period_s`` in a background task until :meth:`stop_watchdog`.

        A failing refresh is logged and kept in ``watchdog_error``; the task keeps trying (the
        controller will stop the motor on its own if the link stays down).  Over a transport whose
        peer refreshes the watchdog itself (``PeerKeptWatchdog``) the drive is refreshed by one
        keeper only: this one asks the peer whether its refreshes go through.
        """
        await self.stop_watchdog()
        peer = self.transport if isinstance(self.transport, PeerKeptWatchdog) else None

        async def keeper() -> None:
            while True:
                try:
                    if peer is not None:
                        await peer.watchdog_status()
                    else:
                        await self.refresh_watchdog()
                    self.watchdog_error = None
                except MotorError as exc:
                    log.error("watchdog refresh failed: %s", exc)
                    self.watchdog_error = exc
                await self.clock.asleep(period_s)

        self._wd_task = self.clock.start_task(keeper(), "motor-watchdog")

    async def stop_watchdog(self) -> None:
        if self._wd_task is not None:
            self._wd_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._wd_task
            self._wd_task = None
