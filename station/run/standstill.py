"""The drive read back after a stop: a stop is verified by the drive's own report of standstill,
never assumed from the command having been taken.  Used after every stop the station gives (a
run's end, an abort, a fault, a lost link, the emergency stop, the shutdown)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from drivers.motor.controller import MotorController, MotorStatus

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DriveCheck:
    """The drive read back after a stop: ``standstill`` True (at rest), False (still turning after
    ``waited_s``) or None (not readable: ``error``); ``at`` is UNIX time."""

    after: str  # which stop, e.g. "the emergency stop"
    standstill: bool | None
    speed_hz: float | None
    fault_code: int | None
    fault_name: str | None
    waited_s: float
    at: float
    error: str | None = None

    @classmethod
    def of(cls, after: str, st: MotorStatus, waited_s: float) -> DriveCheck:
        return cls(after, st.standstill, st.actual_speed_hz, st.fault_code, st.fault_name, waited_s, time.time())

    def describe(self) -> str:
        if self.standstill is None:
            return f"the drive could not be read back after {self.after} ({self.error})"
        if self.standstill:
            return f"the drive reports standstill after {self.after}"
        return (f"the crank still turns at {self.speed_hz:g} Hz {self.waited_s:.1f} s after {self.after} "
                "(the drive does not stop)")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> DriveCheck:
        """The inverse of :meth:`to_dict` (a read-back made in another process)."""
        return cls(str(d["after"]), d["standstill"], d["speed_hz"], d["fault_code"], d["fault_name"],
                   float(d["waited_s"]), datetime.fromisoformat(d["at"]).timestamp(), d.get("error"))

    def to_dict(self) -> dict[str, Any]:
        """For /health."""
        return {"after": self.after, "standstill": self.standstill, "speed_hz": self.speed_hz,
                "fault_code": self.fault_code, "fault_name": self.fault_name, "waited_s": round(self.waited_s, 3),
                "at": datetime.fromtimestamp(self.at, UTC).isoformat(timespec="milliseconds"),
                "error": self.error, "detail": self.describe()}


async def read_back_standstill(motor: MotorController, after: str, ramp_hz_per_s: float | None = None) -> DriveCheck:
    """Read the drive until it reports standstill, for as long as a healthy drive may take from the
    speed it reports now (``MotorController.stop_time_bound_s``); link errors give ``standstill`` None."""
    t0 = motor.clock.monotonic()
    try:
        st = await motor.read_status()
        if not st.standstill:
            st = await motor.settle_to_standstill(motor.stop_time_bound_s(st.actual_speed_hz, ramp_hz_per_s))
    except Exception as exc:
        return DriveCheck(after, None, None, None, None, motor.clock.monotonic() - t0, time.time(),
                          f"{type(exc).__name__}: {exc}")
    check = DriveCheck.of(after, st, motor.clock.monotonic() - t0)
    if check.standstill is False:
        log.error("%s", check.describe())
    return check
