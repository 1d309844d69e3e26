"""The crank motor-controller driver: one interface, the backend (transport) chosen at connect time.

Usage (asyncio)::

    motor = MotorController()                              # register map from config/
    await motor.connect(ModbusTransport.tcp("127.0.0.1", 5020))
    await motor.set_ramp(5.0); await motor.enable(); await motor.set_frequency(20.0)
    status = await motor.read_status()                     # MotorStatus
    ...
    await motor.stop(); await motor.close()

The station must refresh the controller's watchdog: call :meth:`refresh_watchdog` at least every
``watchdog_timeout`` (or run :meth:`start_watchdog`); otherwise the controller stops the motor.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass

from drivers.clock import REAL_CLOCK, Clock
from drivers.motor.errors import MotorError, MotorFaultError, MotorStateError, MotorValueError
from drivers.motor.registers import RegisterMap, load_register_map
from drivers.motor.transport import RegisterTransport

log = logging.getLogger(__name__)

STATUS_BLOCK = ("actual_speed", "crank_angle", "status_word", "fault_code", "revolution_count")


@dataclass(frozen=True)
class MotorStatus:
    """One consistent read of the status block.

    actual_speed_hz: crank frequency in Hz (rev/s); crank_angle_rad in [0, 2*pi);
    flags: decoded status word; fault_code 0 = none; time_s: the driver's clock (``time.monotonic()`` on
    a real rig) at the middle of the request (the angle's timestamp, to within half the round trip ``round_trip_s``).
    """

    actual_speed_hz: float
    crank_angle_rad: float
    status_word: int
    flags: Mapping[str, bool]
    fault_code: int
    fault_name: str
    revolution_count: int
    time_s: float
    round_trip_s: float

    @property
    def crank_angle_deg(self) -> float:
        return math.degrees(self.crank_angle_rad)

    @property
    def standstill(self) -> bool:
        """The crank does not turn (speed 0, status bit ``running`` clear)."""
        return self.actual_speed_hz == 0.0 and not self.flags.get("running", False)

    @property
    def estop_latched(self) -> bool:
        return bool(self.flags.get("estop_active", False))

    def describe(self) -> str:
        """One line for logs and error messages, e.g. ``standstill, disabled, fault 2 (emergency_stop)``."""
        parts = ["standstill" if self.standstill else f"turning at {self.actual_speed_hz:g} Hz",
                 "enabled" if self.flags.get("enabled") else "disabled",
                 f"fault {self.fault_code} ({self.fault_name})" if self.fault_code else "no fault"]
        if self.estop_latched:
            parts.append("emergency stop latched")
        return ", ".join(parts)


class MotorController:
    """Driver of the crank motor controller over any :class:`RegisterTransport`."""

    def __init__(self, regmap: RegisterMap | None = None, *, clock: Clock = REAL_CLOCK) -> None:
        """``clock``: time of the status stamps, the watchdog keeper and ``wait_for_speed`` (real time,
        or the virtual clock of an in-process simulated rig)."""
        self.map = regmap or load_register_map()
        self.clock = clock
        self._t: RegisterTransport | None = None
        self._wd_counter = 0
        self._wd_task: asyncio.Task[None] | None = None
        self.watchdog_error: MotorError | None = None

    @property
    def transport(self) -> RegisterTransport:
        if self._t is None:
            raise MotorError("motor controller not connected: call connect(transport) first")
        return self._t

    async def connect(self, transport: RegisterTransport) -> None:
        """Attach the backend (Modbus TCP/RTU or in-process) and open it."""
        await transport.open()
        self._t = transport
        log.info("motor controller connected via %s", transport.description)

    async def close(self) -> None:
        await self.stop_watchdog()
        if self._t is not None:
            await self._t.close()
            self._t = None

    # --------------------------------------------------------------- register level
    async def read(self, name: str) -> float:
        """Physical value of one register, in its unit (see the register map)."""
        reg = self.map[name]
        return reg.decode(await self.transport.read(reg.address, reg.words, name))

    async def write(self, name: str, value: float) -> None:
        """Write one register (physical value in its unit).

        A value outside the register's declared range (config/motor_registers.yaml ``min``/``max``)
        is refused here, before anything is sent (:class:`MotorValueError`)."""
        reg = self.map[name]
        if not reg.writable:
            raise MotorValueError(f"register {name!r} is read-only")
        reg.check(value)
        await self.transport.write(reg.address, reg.encode(value), name)

    # --------------------------------------------------------------- commands
    async def enable(self) -> None:
        """Enable the drive (it follows the setpoint; the watchdog starts counting)."""
        await self.write("enable", 1)

    async def disable(self) -> None:
        await self.write("enable", 0)

    async def set_frequency(self, hz: float) -> None:
        """Crank-frequency setpoint in Hz; checked against the register's range before sending."""
        await self.write("frequency_setpoint", hz)

    async def set_ramp(self, hz_per_s: float) -> None:
        """Acceleration ramp in Hz/s (magnitude), within the register's range (0 < ramp <= max)."""
        await self.write("acceleration_ramp", hz_per_s)

    async def set_watchdog_timeout(self, seconds: float) -> None:
        """Watchdog timeout in s; 0 (off) is refused while the drive is enabled (checked here first,
        :class:`MotorStateError`; the controller refuses it too, exception 04)."""
        self.map["watchdog_timeout"].check(seconds)
        if seconds == 0 and await self.read("enable") != 0:
            raise MotorStateError("watchdog_timeout: expected a timeout > 0 s while the drive is enabled, "
                                  "got 0 (the watchdog cannot be switched off while enabled)")
        await self.write("watchdog_timeout", seconds)

    async def refresh_watchdog(self) -> None:
        """Write the next value of the rolling watchdog counter."""
        self._wd_counter = (self._wd_counter + 1) & 0xFFFF
        await self.write("watchdog", self._wd_counter)

    async def stop(self) -> None:
        """Normal stop: setpoint 0, then disable; the drive ramps down at the configured ramp."""
        await self.write("frequency_setpoint", 0.0)
        await self.disable()

    async def emergency_stop(self) -> None:
        """Emergency stop: latched; the drive decelerates at its stop ramp.  Clear with reset_faults."""
        await self.write("emergency_stop", 1)

    async def reset_faults(self) -> None:
        """Clear latched faults (the controller refuses while the crank still turns)."""
        await self.write("fault_reset", 1)

    async def read_status(self) -> MotorStatus:
        """Read speed, angle, status word, fault code and revolution count in one request."""
        start, count = self.map.span(STATUS_BLOCK)
        t0 = self.clock.monotonic()
        words = await self.transport.read(start, count, "status block (" + ", ".join(STATUS_BLOCK) + ")")
        t1 = self.clock.monotonic()

        def get(name: str) -> float:
            reg = self.map[name]
            return reg.decode(words[reg.address - start: reg.address - start + reg.words])

        angle_reg = self.map["crank_angle"]
        angle = get("crank_angle")
        angle_rad = math.radians(angle) if angle_reg.unit == "deg" else angle
        word = int(get("status_word"))
        fault = int(get("fault_code"))
        return MotorStatus(
            actual_speed_hz=get("actual_speed"),
            crank_angle_rad=angle_rad % (2 * math.pi),
            status_word=word,
            flags=self.map.decode_status(word),
            fault_code=fault,
            fault_name=self.map.fault_name(fault),
            revolution_count=int(get("revolution_count")),
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
        controller will stop the motor on its own if the link stays down).
        """
        await self.stop_watchdog()

        async def keeper() -> None:
            while True:
                try:
                    await self.refresh_watchdog()
                    self.watchdog_error = None
                except MotorError as exc:
                    log.error("watchdog refresh failed: %s", exc)
                    self.watchdog_error = exc
                await self.clock.asleep(period_s)

        self._wd_task = asyncio.create_task(keeper(), name="motor-watchdog")

    async def stop_watchdog(self) -> None:
        if self._wd_task is not None:
            self._wd_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._wd_task
            self._wd_task = None
