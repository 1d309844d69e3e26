"""The daemon's one connection to the rig: connected at start-up, checked before every run,
reconnected when a link went bad, and the emergency stop on the motor controller.

The connection lives on the rig thread's loop (``rigthread.py``): the drivers' tasks (the motor
watchdog keeper) run there, and every method below hands its work over to it."""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import time
from collections.abc import Callable

from station.config import StationConfig
from station.run.rig import ConnectedRig, connect
from station.run.standstill import DriveCheck, read_back_standstill
from station.service.errors import RigUnavailableError
from station.service.rigthread import RigThread

log = logging.getLogger(__name__)

STANDSTILL_WAIT_S = 10.0  # an acknowledgement waits at most this long for the crank to come to rest

RigConnector = Callable[[StationConfig, bool], contextlib.AbstractAsyncContextManager[ConnectedRig]]


def default_connector(cfg: StationConfig, sim: bool) -> contextlib.AbstractAsyncContextManager[ConnectedRig]:
    return connect(cfg, sim=sim)


def device_of(exc: BaseException) -> str | None:
    """Which device (``"motor"`` or ``"daq"``) a connection failure ``exc`` is of: the one a
    :class:`~station.errors.HardwareMismatchError` names, else by the driver's exception type; None
    when it is neither driver's (the health then shows it under both devices)."""
    from drivers.daq.link import DaqLinkError
    from drivers.motor.errors import MotorError

    device = getattr(exc, "device", None)  # HardwareMismatchError names its device
    if isinstance(device, str):
        return device
    if isinstance(exc, MotorError):
        return "motor"
    if isinstance(exc, DaqLinkError | OSError) or type(exc).__module__.startswith("drivers.daq"):
        return "daq"
    return None


class RigLink:
    """Holds the connected rig (``rig``, None while not connected; ``error`` says why)."""

    def __init__(self, cfg: StationConfig, sim: bool, connector: RigConnector = default_connector,
                 thread: RigThread | None = None) -> None:
        self.cfg = cfg
        self.sim = sim
        self._connector = connector
        self.thread = thread or RigThread()
        self.rig: ConnectedRig | None = None
        self.error: str | None = None
        self.error_device: str | None = None  # "motor", "daq" or None (unknown) for ``error``
        self._stack: contextlib.AsyncExitStack | None = None
        self._lock: asyncio.Lock | None = None  # created on the rig loop
        self.drive: DriveCheck | None = None  # the last read-back after a stop

    def _rig_lock(self) -> asyncio.Lock:
        if self._lock is None:
            self._lock = asyncio.Lock()
        return self._lock

    async def connect(self) -> ConnectedRig | None:
        return await self.thread.start().call(self._connect())

    async def _connect(self) -> ConnectedRig | None:
        async with self._rig_lock():
            if self.rig is not None:
                return self.rig
            stack = contextlib.AsyncExitStack()
            try:
                self.rig = await stack.enter_async_context(self._connector(self.cfg, self.sim))
            except Exception as exc:
                await stack.aclose()
                self.error = f"{type(exc).__name__}: {exc}"
                self.error_device = device_of(exc)
                log.error("cannot connect to the rig: %s", self.error)
                return None
            self._stack, self.error = stack, None
            log.info("connected: %s", self.rig.description)
            return self.rig

    async def disconnect(self) -> None:
        if self.thread.running:
            await self.thread.call(self._disconnect())

    async def _disconnect(self) -> None:
        async with self._rig_lock():
            stack, self._stack, self.rig = self._stack, None, None
            if stack is not None:
                try:
                    await stack.aclose()
                except Exception as exc:
                    log.warning("closing the rig connection: %s", exc)

    @staticmethod
    def healthy(rig: ConnectedRig) -> bool:
        h = rig.health()
        return bool(h["motor"]["connected"]) and not h["motor"]["watchdog_error"] and not h["daq"]["link_error"]

    async def for_run(self) -> ConnectedRig:
        """The connected rig with healthy links (reconnected if needed); RigUnavailableError if none."""
        return await self.thread.start().call(self._for_run())

    async def _for_run(self) -> ConnectedRig:
        rig = self.rig
        if rig is not None and not self.healthy(rig):
            log.warning("rig link unhealthy (%s); reconnecting", rig.health())
            await self._disconnect()
            rig = None
        if rig is None:
            rig = await self._connect()
        if rig is None:
            raise RigUnavailableError(f"the rig is not connected: {self.error}")
        return rig

    def command_emergency_stop(self) -> concurrent.futures.Future[None] | None:
        """Hand the controller's emergency stop to the rig thread's loop now, from any thread but
        the rig thread's (None without a link); :meth:`emergency_stop` awaits it."""
        rig = self.rig
        if rig is None or self.thread.in_thread():
            return None
        try:
            return self.thread.submit(asyncio.wait_for(rig.motor.emergency_stop(), 2.0))
        except RuntimeError:  # the rig thread is not running
            return None

    async def emergency_stop(self, commanded: concurrent.futures.Future[None] | None = None) -> tuple[bool, str]:
        """Command the controller's emergency stop; (taken, what to tell the operator).  The command
        is handed straight to the rig thread's loop (nothing else on the way), or was already
        (``commanded``: :meth:`command_emergency_stop`'s); it answers as soon as the controller took
        it (see :meth:`verify_standstill` for the crank)."""

        rig = self.rig
        if rig is None and commanded is None:
            return False, ("no link to the motor controller; if the crank turns, its watchdog stops it when "
                           "refreshes cease - use the hardware emergency stop")
        try:  # bounded on both sides: a rig loop that does not run cannot hold the answer either
            if commanded is not None:
                await asyncio.wait_for(asyncio.wrap_future(commanded), 3.0)
            else:
                assert rig is not None
                await asyncio.wait_for(self.thread.call(asyncio.wait_for(rig.motor.emergency_stop(), 2.0)), 3.0)
            return True, "emergency stop commanded on the motor controller"
        except Exception as exc:
            return False, (f"the motor controller did not take the emergency stop ({type(exc).__name__}: {exc}); "
                           "use the hardware emergency stop")

    async def verify_standstill(self, after: str, ramp_hz_per_s: float | None = None) -> DriveCheck | None:
        """Read the drive back until it reports standstill (bounded, see ``read_back_standstill``;
        ``ramp_hz_per_s``: the deceleration of the stop given, default the emergency stop's); kept
        in ``drive`` for /health.  None without a link."""
        rig = self.rig
        if rig is None:
            return None
        motor = rig.motor
        bound = motor.stop_time_bound_s(motor.map.device.max_frequency_hz, ramp_hz_per_s) + 2.0
        try:
            check = await asyncio.wait_for(
                self.thread.call(asyncio.wait_for(read_back_standstill(motor, after, ramp_hz_per_s), bound)),
                bound + 1.0)
        except Exception as exc:
            check = DriveCheck(after, None, None, None, None, bound, time.time(), f"{type(exc).__name__}: {exc}")
        self.drive = check
        return check

    async def motor_fault(self) -> tuple[int, str] | None:
        """The controller's latched fault (code, name), read without clearing it; None when there is
        none or the controller cannot be reached."""
        rig = self.rig
        if rig is None:
            return None
        try:
            st = await self.thread.call(asyncio.wait_for(rig.motor.read_state(), 2.0))
        except Exception as exc:
            log.warning("cannot read the motor status: %s", exc)
            return None
        return (st.fault_code, st.fault_name) if st.fault_code else None

    async def reset_faults(self) -> tuple[bool, str]:
        """An operator's acknowledgement: clear the controller's latched faults, then read back.
        (True, detail) when the controller reports no fault afterwards (or there is no link)."""
        rig = self.rig
        if rig is None:
            return True, "no link to the motor controller: its faults are checked at the next connect"

        async def go() -> tuple[bool, str]:
            # only at standstill, fault or none: the crank may still coast down (the flag: below 0.01 Hz too),
            # for as long as a healthy drive needs from the speed it reports (a drive that does not stop
            # is not waited for in vain)
            motor = rig.motor
            st = await motor.read_status()
            if not st.standstill:
                ramp = min(self.cfg.rig.acceleration_hz_per_s, motor.map.device.stop_deceleration_hz_per_s)
                st = await motor.settle_to_standstill(min(STANDSTILL_WAIT_S,
                                                          motor.stop_time_bound_s(st.actual_speed_hz, ramp)))
            self.drive = DriveCheck.of("the acknowledgement", st, 0.0)
            before = f"{st.fault_code} ({st.fault_name})"
            if not st.standstill:
                return False, (f"the crank still turns at {st.actual_speed_hz:g} Hz"
                               + (f"; fault {before} can be reset at standstill only" if st.fault_code else
                                  "; an acknowledgement needs the crank at rest"))
            if not st.fault_code:
                return True, "the motor controller reports no fault"
            try:
                await rig.motor.reset_faults()
            except Exception as exc:
                return False, f"the motor controller refused to reset fault {before}: {exc}"
            st = await rig.motor.read_status()
            if st.fault_code:
                return False, (f"the motor controller still reports fault {st.fault_code} ({st.fault_name}) "
                               f"after the reset (crank still turning at {st.actual_speed_hz:g} Hz?)")
            return True, f"motor controller fault {before} reset"
        async def go_and_release() -> tuple[bool, str]:
            ok, detail = await go()
            if ok and rig.release is not None:  # the rig process holds the stop until acknowledged
                await rig.release()
            return ok, detail
        try:
            return await self.thread.call(asyncio.wait_for(go_and_release(), STANDSTILL_WAIT_S + 5.0))
        except Exception as exc:
            return False, f"the motor controller cannot be reached ({type(exc).__name__}: {exc})"

    async def stop_motor(self) -> None:
        """Ramp the crank down and read it back (shutdown path; errors ignored, a crank still
        turning logged)."""
        rig = self.rig
        if rig is not None and self.thread.running:
            with contextlib.suppress(Exception):
                await self.thread.call(asyncio.wait_for(rig.motor.stop(), 3.0))
            check = await self.verify_standstill("the shutdown's stop", self.cfg.rig.acceleration_hz_per_s)
            if check is not None and check.standstill is False:
                with contextlib.suppress(Exception):
                    await self.thread.call(asyncio.wait_for(rig.motor.emergency_stop(), 2.0))

    async def close(self) -> None:
        """Disconnect and end the rig thread."""
        await self.disconnect()
        await asyncio.to_thread(self.thread.stop)
