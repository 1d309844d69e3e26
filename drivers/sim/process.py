"""The simulated rig in a process of its own, seen from outside it: :class:`SimRigProcess` runs
``python -m drivers.sim`` and reads the addresses it prints (:class:`SimRigAddresses`); through its
control channel it reads the motor's true state, makes the drive ignore stops, loads other physics,
changes the crank radius and (``commands=True``) logs every command the controller takes with its time.

Nothing of the emulators is imported here: the daemon that starts the process loads none of them.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import os
import pickle
import socket
import subprocess
import sys
import threading
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from drivers.rig.params import RigPhysics


@dataclass(frozen=True)
class SimRigAddresses:
    """Where the emulators listen: Modbus TCP (host, port), Modbus RTU pty path, DAQ pty path, and
    the control socket (``status``, ``radius R``: :class:`SocketCrankRadius`; None when not served)."""

    modbus_tcp: tuple[str, int]
    modbus_rtu: str | None
    daq: str
    control: str | None = None

    @property
    def modbus_tcp_url(self) -> str:
        return f"modbus-tcp://{self.modbus_tcp[0]}:{self.modbus_tcp[1]}"

    @property
    def modbus_rtu_url(self) -> str | None:
        """The RTU pty as a URL; 8N2, since a pty refuses even parity (see drivers.sim.motor_server)."""
        return None if self.modbus_rtu is None else f"modbus-rtu://{self.modbus_rtu}?parity=N"


class SimRigProcess:
    """``python -m drivers.sim`` in a subprocess; ``addresses`` parsed from its first stdout line.

    ``commands=True``: every command the motor controller takes is collected (``commands``: name,
    value, ``time.monotonic()`` when applied, one clock for every process) and can be waited for
    (:meth:`wait_command`).  :meth:`status` reads the motor's true state, :meth:`ignore_stops` is the
    fault hook of ``MotorModel.ignore_stops`` across the process boundary."""

    def __init__(self, *, seed: int = 0, modbus_port: int = 0, crank_radius_m: float = 0.01,
                 commands: bool = False, profile: str | None = None, daq_link: str = "uart") -> None:
        """``profile``: the drive profile the motor emulator behaves as (a shipped name or a YAML
        path; default the station's own); ``daq_link``: the link kind the bridge reports."""
        self._args = [sys.executable, "-m", "drivers.sim", "--json", "--seed", str(seed),
                      "--modbus-port", str(modbus_port), "--crank-radius", str(crank_radius_m),
                      "--daq-link", daq_link]
        if profile is not None:
            self._args += ["--profile", profile]
        if commands:
            self._args.append("--commands")
        self._proc: subprocess.Popen[str] | None = None
        self._cond = threading.Condition()
        self._replies: list[dict[str, Any]] = []
        self.commands: list[tuple[str, float, float]] = []
        self.addresses: SimRigAddresses

    def launch(self) -> SimRigProcess:
        """Start the subprocess without waiting for it (:meth:`__enter__` waits until it serves)."""
        if self._proc is None:
            self._proc = subprocess.Popen(self._args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                          bufsize=1, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        return self

    def __enter__(self) -> SimRigProcess:
        self.launch()
        assert self._proc is not None and self._proc.stdout is not None
        line = self._proc.stdout.readline()
        if not line:
            rc = self._proc.wait()
            raise RuntimeError(f"sim rig subprocess exited with {rc} before printing addresses")
        d = json.loads(line)
        self.addresses = SimRigAddresses(tuple(d["modbus_tcp"]), d["modbus_rtu"], d["daq"], d.get("control"))
        threading.Thread(target=self._read, name="sim-rig-process-reader", daemon=True).start()
        return self

    def _read(self) -> None:
        assert self._proc is not None and self._proc.stdout is not None
        for line in self._proc.stdout:
            d = json.loads(line)
            with self._cond:
                if "command" in d:
                    self.commands.append((d["command"], d["value"], d["t_monotonic"]))
                else:
                    self._replies.append(d)
                self._cond.notify_all()

    def _ask(self, line: str, timeout_s: float = 5.0) -> dict[str, Any]:
        assert self._proc is not None and self._proc.stdin is not None
        with self._cond:
            n = len(self._replies)
            self._proc.stdin.write(line + "\n")
            self._proc.stdin.flush()
            if not self._cond.wait_for(lambda: len(self._replies) > n, timeout_s):
                raise TimeoutError(f"the sim rig process did not answer {line!r}")
            return self._replies[n]

    def status(self) -> dict[str, Any]:
        """The motor's true state: speed_hz, enabled, fault_code, estop, watchdog_refreshes, radius_m
        (the crank radius synthesised), t_monotonic."""
        return dict(self._ask("status")["status"])

    def ignore_stops(self, on: bool = True) -> None:
        self._ask(f"ignore-stops {'on' if on else 'off'}")

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def load_physics(self, physics: RigPhysics) -> None:
        """Synthesise ``physics`` from now on (see :meth:`SimRig.load_physics`); RuntimeError if refused."""
        reply = self._ask("load " + base64.b64encode(pickle.dumps(physics)).decode("ascii"))
        if "error" in reply:
            raise RuntimeError(reply["error"])

    def set_crank_radius(self, radius_m: float) -> None:
        """Change the crank radius (m) once the crank is at rest (see :meth:`SimRig.change_crank_radius`)."""
        reply = self._ask(f"radius {radius_m!r}", timeout_s=10.0)
        if "error" in reply:
            raise RuntimeError(reply["error"])

    def radius_actuator(self, radius_m: float) -> ProcessCrankRadius:
        """The crank-radius actuator of this rig for the run procedure (its radius now: ``radius_m``)."""
        return ProcessCrankRadius(self, radius_m)

    def wait_command(self, name: str, after: float, timeout_s: float = 10.0) -> float | None:
        """``time.monotonic()`` at which the controller took the first ``name`` command applied at or
        after ``after``; None if none within ``timeout_s``."""
        def found() -> float | None:
            return next((t for n, _, t in self.commands if n == name and t >= after), None)
        with self._cond:
            self._cond.wait_for(lambda: found() is not None, timeout_s)
            return found()

    def __exit__(self, *exc: object) -> None:
        if self._proc is not None:
            assert self._proc.stdin is not None
            with contextlib.suppress(OSError):
                self._proc.stdin.close()  # EOF on stdin ends the subprocess
            try:
                self._proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()


class ProcessCrankRadius:
    """The motorised crank radius of a simulated rig in another process (see :class:`SimCrankRadius`)."""

    def __init__(self, rig: SimRigProcess, radius_m: float) -> None:
        self._rig = rig
        self.radius_m = radius_m

    async def set_radius(self, radius_m: float) -> None:
        await asyncio.to_thread(self._rig.set_crank_radius, radius_m)
        self.radius_m = radius_m


class SocketCrankRadius:
    """The motorised crank radius of a simulated rig reached on its control socket (``addresses.control``),
    from a process that did not start the emulators (the rig process)."""

    TIMEOUT_S = 10.0  # the emulator waits up to 3 s for standstill, then moves the eccentric

    def __init__(self, control: str, radius_m: float) -> None:
        self.control = control
        self.radius_m = radius_m

    async def set_radius(self, radius_m: float) -> None:
        reply = await asyncio.to_thread(self._ask, f"radius {float(radius_m)!r}")
        if "error" in reply:
            raise RuntimeError(f"the simulated rig did not change the crank radius: {reply['error']}")
        self.radius_m = radius_m

    def _ask(self, line: str) -> dict[str, Any]:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(self.TIMEOUT_S)
            s.connect(self.control)
            s.sendall(line.encode("ascii") + b"\n")
            with s.makefile("rb") as f:
                answer = f.readline(4096)
        if not answer:
            return {"error": "the control socket closed without an answer"}
        reply: dict[str, Any] = json.loads(answer)
        return reply


def addresses_json(addr: SimRigAddresses, control: str | None = None) -> str:
    """The addresses line (``control``: the control socket's path, served by ``python -m drivers.sim``)."""
    return json.dumps({**asdict(addr), "control": control or addr.control})
