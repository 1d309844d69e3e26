"""Every shipped drive profile, end to end: the driver and the emulator both read the profile, so the
drivers' fault matrix and a simulated calibration run against each drive (in-process on the virtual
clock; the wire for a subset), EEPROM-backed registers are never written in a loop, a profile added
from YAML alone runs, and one frame per profile is checked byte by byte against the drive's manual.
"""

from __future__ import annotations

import asyncio
import copy
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from drivers.motor import (
    LinkPolicy,
    ModbusTransport,
    MotorController,
    MotorExceptionReplyError,
    MotorStateError,
    MotorValueError,
    load_profile,
    shipped_profiles,
)
from drivers.motor.errors import RegisterMapError
from drivers.motor.profile import parse_profile, profile_path
from drivers.sim.clock import VirtualClock
from drivers.sim.motor_image import MotorRegisterImage
from drivers.sim.motor_inprocess import InProcessTransport
from drivers.sim.motor_model import FAULT_ESTOP, MotorModel
from station.config import parse_config
from station.errors import ConfigError, LimitError
from station.recording import read_recording
from station.run.procedure import Procedure
from station.run.request import Plan, PlannedStep, RunRequest, StepSpec, plan_run
from station.run.rig import connect
from tests.drive_support import calibration_config, drive

ROOT = Path(__file__).resolve().parent.parent
PROFILES = shipped_profiles()


def test_the_four_drives_and_the_station_controller_are_shipped() -> None:
    assert set(PROFILES) >= {"sinecal-crank", "toshiba-vf-s11", "automationdirect-gs2", "siemens-sinamics-v20",
                             "cia402-modbus"}
    for name in PROFILES:
        p = load_profile(name)
        assert p.name == name and p.watchdog.timeout_s > 0 and p.sources


# ------------------------------------------------------------------------------------ in-process rig
async def spin_up(motor: MotorController, hz: float = 20.0) -> None:
    await motor.ensure_watchdog()
    await motor.set_ramp(50.0)
    await motor.enable()
    await motor.set_frequency(hz)
    st = await motor.wait_for_speed(hz, timeout_s=5.0)
    assert st.flags["enabled"] and st.flags["running"] and not st.standstill


@pytest.mark.parametrize("name", PROFILES)
def test_fault_matrix_on_every_profile(name: str) -> None:
    """The drivers' fault matrix, per drive: a lost link stops the crank by the drive's own watchdog;
    an emergency stop latches and is cleared only at standstill; an injected drive fault is reported
    with the drive's code; out-of-range values are refused by the driver and by the drive; the
    watchdog cannot be switched off while enabled."""
    p = load_profile(name)

    async def body(motor: MotorController, model: MotorModel, image: MotorRegisterImage, clock: VirtualClock) -> None:
        # 1. out-of-range set point: the driver refuses before sending, the drive answers 03
        with pytest.raises(MotorValueError, match="expected"):
            await motor.set_frequency(p.device.max_frequency_hz + 1.0)
        sp = p[p.setpoint]
        assert image.write(sp.address, sp.words_of_raw(sp.raw_range()[1])) == 0x03
        # 2. a started drive cannot have its watchdog switched off
        await spin_up(motor)
        with pytest.raises(MotorStateError, match="while the drive is enabled"):
            await motor.set_watchdog_timeout(0)
        if p.watchdog.min_s > p[p.watchdog.register].scale:
            with pytest.raises(MotorValueError, match="at least the drive's smallest time-out"):
                await motor.set_watchdog_timeout(0.5 * p.watchdog.min_s)
        # 3. emergency stop: latched, the crank decelerates; reset refused while it turns
        await motor.emergency_stop()
        st = await motor.read_status()
        assert st.flags["estop"] and st.fault_code != 0 and st.fault_name
        assert st.estop_latched and not st.flags["enabled"]
        if model.speed_hz() != 0:
            with pytest.raises(MotorExceptionReplyError, match="0x04"):
                await motor.reset_faults()
        await motor.wait_for_speed(0.0, timeout_s=5.0)
        await motor.reset_faults()
        st = await motor.check_standstill()
        assert st.fault_code == 0 and not st.flags["estop"]
        # 4. an injected overcurrent is reported with the drive's code for it
        await spin_up(motor)
        model.inject_fault(3)
        st = await motor.read_status()
        want = p.faults.kinds.get("overcurrent")
        assert st.flags["fault"] and (want is None or st.fault_code == want), st.describe()
        await motor.wait_for_speed(0.0, timeout_s=5.0)
        await motor.reset_faults()
        # 5. the link is lost: the drive's watchdog stops the crank on its own
        await spin_up(motor)
        transport = motor.transport
        assert isinstance(transport, InProcessTransport)
        transport.cut()
        await clock.asleep(p.watchdog.timeout_s + 20.0 / p.device.stop_deceleration_hz_per_s + 0.5)
        snap = model.snapshot()
        assert snap.speed_hz == 0.0 and snap.watchdog_expired and not snap.enabled

    image = drive(p, body)
    assert image.commands_seen.count("quick_stop") == 1 and "fault_reset" in image.commands_seen


@pytest.mark.parametrize("name", PROFILES)
def test_eeprom_registers_are_never_written_in_a_loop(name: str) -> None:
    """Parameters are set when they change: the same ramp and watchdog set 5 times write an EEPROM
    register once; a loop of changing values is refused after a few writes."""
    p = load_profile(name)
    eeprom = [r.name for r in p.registers.values() if r.eeprom and r.writable]

    async def body(motor: MotorController, model: MotorModel, image: MotorRegisterImage, clock: VirtualClock) -> None:
        for _ in range(5):
            await motor.set_ramp(20.0)
            await motor.ensure_watchdog()
        assert all(image.writes[n] <= 1 for n in eeprom), dict(image.writes)
        if p.ramp is not None and p[p.ramp.registers[0]].eeprom:
            with pytest.raises(MotorValueError, match="EEPROM-backed and was written"):
                for k in range(10):
                    await motor.set_ramp(10.0 + k)
            assert image.writes[p.ramp.registers[0]] <= 4

    drive(p, body)


def test_control_word_steps_held_too_briefly_are_not_seen_by_the_drive() -> None:
    """The CiA 402 enable sequence written without its hold times does not enable the emulated drive;
    "enable operation" alone runs a drive that is switched on, and only then."""
    p = load_profile("cia402-modbus")
    cw = p[p.commands.sequences["enable"][1].register]

    async def body(motor: MotorController, model: MotorModel, image: MotorRegisterImage, clock: VirtualClock) -> None:
        await motor.ensure_watchdog()
        for word in (0x0006, 0x0007, 0x000F):  # no pause: not held for hold_s
            await motor.transport.write(cw.address, [word], cw.name)
        assert not (await motor.read_status()).flags["enabled"]
        await motor.enable()  # with the hold times: shutdown, switch on, then "run" (enable operation)
        assert (await motor.read_status()).flags["enabled"]
        await motor.disable()  # disable operation (0x07): stays switched on ...
        st = await motor.read_status()
        assert not st.flags["enabled"] and st.flags["switched_on"] and st.status_word & 0x6F == 0x23
        await motor.transport.write(cw.address, [0x000F], cw.name)  # ... so enable operation alone runs
        assert (await motor.read_status()).flags["enabled"]
        await motor.emergency_stop()  # quick stop: no longer switched on
        await motor.wait_for_speed(0.0, timeout_s=5.0)
        await motor.transport.write(cw.address, [0x000F], cw.name)
        assert not (await motor.read_status()).flags["enabled"]

    drive(p, body)


# ------------------------------------------------------------------------------ a calibration per drive
def calibrate(tmp_path: Path, profile: str, *, wire: bool = False) -> tuple[object, dict[str, int], list[str]]:
    cfg = parse_config(calibration_config(profile), "test.yaml")
    steps = [StepSpec(crank_frequency_hz=s.crank_frequency_hz, crank_radius_m=s.crank_radius_m)
             for s in cfg.plan.steps]
    plan = plan_run(cfg, RunRequest(transducer_id=cfg.transducer.id, top_mass_kg=cfg.rig.top_mass_kg, steps=steps))

    async def go() -> tuple[object, dict[str, int], list[str]]:
        async with connect(plan.config, sim=True, first_radius_m=steps[0].crank_radius_m,
                           sim_clock=None if wire else VirtualClock()) as rig:
            assert rig.sim is not None and rig.motor.profile.name == load_profile(profile).name == rig.sim.map.name
            outcome = await Procedure(plan, rig, tmp_path).execute()
            return outcome, dict(rig.sim.image.writes), list(rig.sim.image.commands_seen)

    return asyncio.run(go())


@pytest.mark.parametrize("name", PROFILES)
@pytest.mark.slow
def test_simulated_calibration_on_every_profile(tmp_path: Path, name: str) -> None:
    outcome, writes, commands = calibrate(tmp_path, name)
    assert outcome.exit_status == "completed", outcome.reason  # type: ignore[attr-defined]
    p = load_profile(name)
    assert all(writes.get(r.name, 0) <= 1 for r in p.registers.values() if r.eeprom), writes
    assert commands.count("enable") >= 1 and commands[-1] == "stop"
    with h5py.File(outcome.path, "r") as f:  # type: ignore[attr-defined]  # the profile it was driven with
        assert bytes(f["config/drive_profile"][...]).decode() == profile_path(name).read_text(encoding="utf-8")
    rec = read_recording(outcome.path)  # type: ignore[attr-defined]
    assert rec.complete and len(rec.steps) == 2 and rec.lost_samples.size == 0
    for st in rec.steps:  # each window holds a steady sine at the step's frequency
        d, _ = rec.step_signals(st)
        spec = np.abs(np.fft.rfft(d - d.mean()))
        assert np.argmax(spec) * 20_000 / d.size == pytest.approx(st.crank_frequency_hz, abs=2.0)


@pytest.mark.slow
@pytest.mark.waits  # a run over Modbus TCP in real time: about 4.5 s of wall time, 0.5 s of CPU
@pytest.mark.parametrize("name", ["toshiba-vf-s11", "siemens-sinamics-v20"])
def test_simulated_calibration_over_modbus_tcp(tmp_path: Path, name: str) -> None:
    """Over the wire in real time: one register per read (VF-S11), Modicon numbering and a normalised
    set point (V20)."""
    outcome, _, _ = calibrate(tmp_path, name, wire=True)
    assert outcome.exit_status == "completed", outcome.reason  # type: ignore[attr-defined]


# ------------------------------------------------------------------------------ a profile from YAML alone
NEW_DRIVE = """
profile: acme-vfd
description: "a drive no code knows: 1-based register numbers, a 0.05 Hz set point with an offset"
sources: ["its manual"]
transport: {kind: tcp, unit_id: 7, functions: [3, 6], max_registers_per_read: 2}
registers:
  run:       {address: 11, numbering: 1, type: uint16, min: 0, max: 3}
  setpoint:  {address: 12, numbering: 1, type: uint16, scale: 0.05, offset: -1.0, unit: Hz, min: 0, max: 45}
  speed:     {address: 21, numbering: 1, type: int16, scale: 0.05, offset: -1.0, unit: Hz, access: r}
  state:     {address: 22, numbering: 1, type: uint16, access: r}
  alarm:     {address: 23, numbering: 1, type: uint16, access: r}
  ramp_time: {address: 31, numbering: 1, type: uint16, scale: 0.1, unit: s, min: 0.2, max: 100, memory: eeprom}
  comm_loss: {address: 32, numbering: 1, type: uint16, scale: 0.1, unit: s, min: 0, max: 10, memory: eeprom}
setpoint: setpoint
speed: speed
ramp: {registers: [ramp_time], form: time_to_max}
status:
  register: state
  flags: {enabled: {bit: 0}, fault: {bit: 7}, estop: {bit: 6}}
faults:
  register: alarm
  codes: {0: none, 17: overcurrent, 40: emergency stop, 41: bus time-out}
  kinds: {emergency_stop: 40, watchdog_expired: 41, overcurrent: 17}
commands:
  model: registers
  enable: [{register: run, value: 1}]
  stop: [{register: run, value: 0}]
  quick_stop: [{register: run, value: 2}]
  fault_reset: [{register: run, value: 3}, {register: run, value: 0}]
watchdog: {register: comm_loss, timeout_s: 1.0, min_s: 0.1}
"""


@pytest.mark.slow
def test_a_profile_added_from_yaml_alone_runs(tmp_path: Path) -> None:
    path = tmp_path / "acme-vfd.yaml"
    path.write_text(NEW_DRIVE)
    p = load_profile(path)
    assert (p["setpoint"].address, p.transport.unit_id) == (11, 7)
    assert p["setpoint"].encode(20.0) == [420]  # (20 + 1) / 0.05

    async def body(motor: MotorController, model: MotorModel, image: MotorRegisterImage, clock: VirtualClock) -> None:
        await spin_up(motor, 30.0)
        assert image.read(11, 1) == [round(31 / 0.05)]  # set point register, wire address 11
        await motor.emergency_stop()
        st = await motor.read_status()
        assert (st.fault_code, st.fault_name) == (40, "emergency stop")
        await motor.wait_for_speed(0.0, timeout_s=5.0)
        await motor.reset_faults()
        assert (await motor.check_standstill()).fault_code == 0

    drive(p, body)
    # and a whole calibration with it, chosen by path in the configuration
    outcome, _, _ = calibrate(tmp_path, str(path))
    assert outcome.exit_status == "completed", outcome.reason  # type: ignore[attr-defined]


def test_a_profile_whose_watchdog_is_off_is_refused(tmp_path: Path) -> None:
    doc = yaml.safe_load(NEW_DRIVE)
    off = copy.deepcopy(doc)
    off["watchdog"]["timeout_s"] = 0
    with pytest.raises(RegisterMapError, match="watchdog is off is refused"):
        parse_profile(off, "acme.yaml")
    path = tmp_path / "off.yaml"
    path.write_text(yaml.safe_dump(off))
    d = calibration_config(str(path))
    with pytest.raises(ConfigError, match=r"rig.motor.profile: .*watchdog is off is refused"):
        parse_config(d, "test.yaml")


def test_steps_beyond_the_drives_range_are_refused_before_anything_moves(tmp_path: Path) -> None:
    d = calibration_config("toshiba-vf-s11")
    d["rig"]["crank_frequency_hz"]["max"] = 100.0
    d["plan"]["steps"][1].update(crank_frequency_hz=60.0, crank_radius_m=0.0002)  # the VF-S11 profile's 50 Hz
    cfg = parse_config(d, "test.yaml")
    steps = [StepSpec(crank_frequency_hz=s.crank_frequency_hz, crank_radius_m=s.crank_radius_m)
             for s in cfg.plan.steps]
    refused = r"step 2 \(60 Hz.*drive profile 'toshiba-vf-s11' can be set to \(0..50 Hz"
    with pytest.raises(LimitError, match=refused) as exc:
        plan_run(cfg, RunRequest(transducer_id=cfg.transducer.id, top_mass_kg=cfg.rig.top_mass_kg, steps=steps))
    e = exc.value
    assert (e.step, e.field, e.value, e.limit) == (1, "crank_frequency_hz", 60.0, (0, 50))
    # the procedure refuses such a plan too, should one reach it by another way than plan_run
    plan = Plan(cfg, tuple(PlannedStep(i, s.crank_frequency_hz, s.crank_radius_m, 0.1, 0.5)
                           for i, s in enumerate(cfg.plan.steps)))

    async def go() -> object:
        async with connect(plan.config, sim=True, first_radius_m=0.002, sim_clock=VirtualClock()) as rig:
            outcome = await Procedure(plan, rig, tmp_path).execute()
            assert rig.sim is not None and "enable" not in rig.sim.image.commands_seen  # never enabled
            assert not any(rig.sim.image.writes[r] for r in ("acceleration_time", "communication_timeout"))
            return outcome

    outcome = asyncio.run(go())
    assert outcome.exit_status == "failed"  # type: ignore[attr-defined]
    assert "expected within what drive profile 'toshiba-vf-s11' can be set to (0..50 Hz)" in outcome.reason  # type: ignore[attr-defined]


# ------------------------------------------------------------------------------ byte-exact frames
class EchoModbusServer:
    """A loopback Modbus TCP peer that records each request and answers FC 03/06/16 as a drive does,
    from a plain register store (``preset``: wire address -> word, the settings made on the panel)."""

    def __init__(self, preset: dict[int, int] | None = None) -> None:
        self.requests: list[str] = []
        self.arrivals: list[float] = []  # time.monotonic() of each request's first byte
        self.regs: dict[int, int] = dict(preset or {})

    def _answer(self, body: bytes) -> bytes:
        fc, addr, qty = body[1], int.from_bytes(body[2:4], "big"), int.from_bytes(body[4:6], "big")
        if fc == 0x06:
            self.regs[addr] = qty
            return body
        if fc == 0x10:
            for i in range(qty):
                self.regs[addr + i] = int.from_bytes(body[7 + 2 * i: 9 + 2 * i], "big")
            return body[:6]
        words = b"".join(self.regs.get(addr + i, 0).to_bytes(2, "big") for i in range(qty))
        return body[:2] + bytes([len(words)]) + words

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                head = await reader.readexactly(6)
                self.arrivals.append(time.monotonic())
                body = await reader.readexactly(int.from_bytes(head[4:6], "big"))
                self.requests.append(body.hex(" ").upper())
                reply = self._answer(body)
                writer.write(head[:4] + len(reply).to_bytes(2, "big") + reply)
                await writer.drain()
        except asyncio.IncompleteReadError:
            return

    async def __aenter__(self) -> tuple[str, int]:
        self.server = await asyncio.start_server(self._handle, "127.0.0.1", 0)
        return self.server.sockets[0].getsockname()[:2]

    async def __aexit__(self, *exc: object) -> None:
        self.server.close()


# unit | function | address | data, from each drive's manual: the set point 20 Hz, then enable
FRAMES = {
    "sinecal-crank": ["01 06 00 01 07 D0", "01 06 00 00 00 01"],
    # FA01 in 0.01 Hz; FA00 = command priority | frequency priority | run
    "toshiba-vf-s11": ["01 06 FA 01 07 D0", "01 06 FA 00 C4 00"],
    # 0x091A in 0.1 Hz; 0x091C direction forward, 0x091B run = 1, then the direction read back
    "automationdirect-gs2": ["01 06 09 1A 00 C8", "01 06 09 1C 00 00", "01 06 09 1B 00 01", "01 03 09 1C 00 01"],
    # HSW 40101 (wire 100): 20/50 x 16384 = 6553.6 -> 6554; STW1 40100 (wire 99): OFF1 then ON
    "siemens-sinamics-v20": ["01 06 00 64 19 9A", "01 06 00 63 04 7E", "01 06 00 63 04 7F"],
    # 0x60FF int32 in 0.1 rev/min (20 rev/s = 12000), high word first, FC 16; mode 3, then 6 -> 7 -> F
    "cia402-modbus": ["01 10 60 FF 00 02 04 00 00 2E E0", "01 06 60 60 00 03", "01 06 60 40 00 06",  # enable, run
                      "01 06 60 40 00 07", "01 06 60 40 00 0F"],
}


# the settings a commissioning engineer makes on the panel (wire address -> word) for the checked ones
PANEL = {"toshiba-vf-s11": {0x0011: 8000, 0x0012: 5000},  # FH 80 Hz, UL 50 Hz
         "siemens-sinamics-v20": {15: 5000}}              # P2000 (40016) 50 Hz


@pytest.mark.parametrize("name", PROFILES)
def test_command_and_set_point_frames_are_byte_exact(name: str) -> None:
    p = load_profile(name)
    fake = EchoModbusServer(PANEL.get(name))
    armed = 0

    async def run() -> None:
        nonlocal armed
        async with fake as (host, port):
            motor = MotorController(p, clock=VirtualClock())
            await motor.connect(ModbusTransport.tcp(host, port, device_id=p.transport.unit_id,
                                                    policy=LinkPolicy(timeout_s=1.0)))
            await motor.arm()
            armed = len(fake.requests)
            await motor.set_frequency(20.0)
            await motor.enable()
            await motor.close()

    asyncio.run(run())
    assert fake.requests[armed:] == FRAMES[name]


def test_the_gs2_is_armed_on_the_wire_as_its_manual_says() -> None:
    """Each safety parameter read, written where it differs from the factory setting, read back:
    P9.04 = 1, P9.03 = 1, P3.00 = 3, P4.00 = 5 (P1.00 is already 0: not written), P9.05 = 1.0 s."""
    fake = EchoModbusServer({0x0905: 5})  # the factory P9.05 = 0.5 s; everything else 0

    async def run() -> dict[str, float]:
        async with fake as (host, port):
            motor = MotorController(load_profile("automationdirect-gs2"), clock=VirtualClock())
            await motor.connect(ModbusTransport.tcp(host, port, policy=LinkPolicy(timeout_s=1.0)))
            found = await motor.arm()
            await motor.close()
            return found

    found = asyncio.run(run())
    writes = [r for r in fake.requests if r[3:5] == "06"]
    assert writes == ["01 06 09 04 00 01", "01 06 09 03 00 01", "01 06 03 00 00 03", "01 06 04 00 00 05",
                      "01 06 09 05 00 0A"]
    assert found == {"P9.04": 1, "P9.03": 1, "P3.00": 3, "P4.00": 5, "P1.00": 0, "P9.05": 1.0}


def test_status_decoding_of_each_drive() -> None:
    """Status words as the manuals define them -> the station's canonical flags."""
    cia = load_profile("cia402-modbus")
    assert cia.decode_status(0x0627)["enabled"] and cia.decode_status(0x0627)["at_setpoint"]
    assert cia.decode_status(0x0008)["fault"] and cia.decode_status(0x000F)["fault"]
    assert cia.decode_status(0x0007)["estop"] and not cia.decode_status(0x0027)["estop"]
    assert cia.decode_status(0x0021)["ready"] and not cia.decode_status(0x0040)["ready"]
    v20 = load_profile("siemens-sinamics-v20")
    assert v20.decode_status(0x0237)["estop"] is False and v20.decode_status(0x0217)["estop"] is True
    assert v20["hsw"].decode([0x4000]) == pytest.approx(50.0) and v20["hiw"].decode([0xC000]) == pytest.approx(-50.0)
    gs2 = load_profile("automationdirect-gs2")
    assert gs2["scale_frequency"].decode([0x86A0, 0x0001]) == pytest.approx(10000.0)  # 100000 low word first
    tosh = load_profile("toshiba-vf-s11")
    flags = tosh.decode_status(0x1002)
    assert flags["estop"] and flags["fault"] and not flags["enabled"]
    assert profile_path("toshiba-vf-s11").name == "toshiba-vf-s11.yaml"


@pytest.fixture
def image_of() -> Iterator[Callable[[str], MotorRegisterImage]]:
    yield lambda name: MotorRegisterImage(load_profile(name), MotorModel(load_profile(name).device, clock=lambda: 0.0))


def test_emulator_refuses_longer_reads_than_the_drive(image_of: Callable[[str], MotorRegisterImage]) -> None:
    img = image_of("toshiba-vf-s11")
    assert img.read(0xFD00, 2) == 0x03 and isinstance(img.read(0xFD00, 1), list)
    assert img.read(0xFD02, 1) == 0x02
    assert FAULT_ESTOP == 2


def test_the_profiles_transport_settings_reach_the_modbus_client() -> None:
    """The profile's character format and unit id are the defaults of the station's motor URL, and its
    inter-frame delay separates every request from the end of the previous exchange."""
    from drivers.motor import transport_from_url

    gs2 = load_profile("automationdirect-gs2").transport

    def line(url: str) -> tuple[str, int, int, int]:
        t = transport_from_url(url, device_id=gs2.unit_id, baudrate=gs2.baudrate, parity=gs2.parity,
                               stopbits=gs2.stopbits)

        async def make() -> tuple[str, int, int, int]:
            p = t._make_client().comm_params
            return p.parity, p.stopbits, p.baudrate, t.device_id
        return asyncio.run(make())

    assert line("modbus-rtu:///dev/ttyUSB0") == ("O", 1, 19200, 1)          # the GS2's 8O1, 19200 Bd
    assert line("modbus-rtu:///dev/ttyUSB0?parity=N&baudrate=9600") == ("N", 2, 9600, 1)  # the URL wins

    fake = EchoModbusServer()

    async def run() -> None:
        async with fake as (host, port):
            t = transport_from_url(f"modbus-tcp://{host}:{port}", inter_frame_delay_s=0.05)
            motor = MotorController(load_profile("automationdirect-gs2"), clock=VirtualClock())
            await motor.connect(t)
            for _ in range(3):
                await motor.set_frequency(10.0)
            await motor.close()

    asyncio.run(run())
    gaps = np.diff(fake.arrivals)
    assert len(gaps) == 2 and gaps.min() >= 0.05  # a lower bound the transport guarantees


@pytest.mark.slow
def test_an_unknown_profile_is_a_clear_error_of_the_commands() -> None:
    import subprocess
    import sys

    for args in (["-m", "station.cli", "sim-rig", "--profile", "no-such-drive"],
                 ["-m", "drivers.sim", "--profile", "no-such-drive"]):
        r = subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=60)
        assert r.returncode != 0 and "Traceback" not in r.stderr
        assert "drive profile 'no-such-drive': expected a shipped profile" in r.stderr


def test_any_malformed_profile_is_a_register_map_error_never_a_crash() -> None:
    """Seeded mutations of every shipped profile (wrong types, missing keys, junk values): each is
    refused with a RegisterMapError or loads; nothing else escapes (bad input gets a clear error)."""
    import random

    junk = [None, "x", -1, 0, 1.5, [], {}, [1], {"a": 1}, {1: 2}, True, 10**9, float("nan"), "0x10", [[1]],
            {"bit": 3}, {"mask": 3, "value": "x"}]

    def paths(d: object, pre: tuple = ()) -> Iterator[tuple]:
        items = d.items() if isinstance(d, dict) else enumerate(d) if isinstance(d, list) else []
        for k, v in items:
            yield (*pre, k)
            yield from paths(v, (*pre, k))

    rng = random.Random(11)
    refused = 0
    for name in PROFILES:
        doc = yaml.safe_load(profile_path(name).read_text())
        where = list(paths(doc))
        for _ in range(60):
            d = copy.deepcopy(doc)
            p = rng.choice(where)
            tgt = d
            for k in p[:-1]:
                tgt = tgt[k]
            if rng.random() < 0.2 and isinstance(tgt, dict):
                del tgt[p[-1]]
            else:
                tgt[p[-1]] = rng.choice(junk)
            try:
                parse_profile(d, "mutated.yaml")
            except RegisterMapError as exc:
                refused += 1
                assert "mutated.yaml" in str(exc) and "expected" in str(exc)
    assert refused > 150  # most mutations break something, and each says what


@pytest.mark.slow
@pytest.mark.parametrize("name", ["cia402-modbus", "siemens-sinamics-v20"])
def test_the_daemon_latches_a_quick_stop_of_a_drive_that_gives_no_code(tmp_path: Path, name: str) -> None:
    """A CiA 402 or V20 quick stop is a state, not a fault code: the daemon still fails the run, latches
    the stop and clears it only when an operator acknowledges; the next run moves the crank."""
    from tests.station_support import (
        CAPPED_SPEEDUP,
        FINAL,
        IDLE_SPEEDUP,
        app_in_process,
        daemon_config,
        run_body,
        start,
        wait_state,
    )

    cfg = daemon_config(tmp_path / "rec")
    cfg["rig"].update(motor={"profile": name}, crank_frequency_hz={"min": 1.0, "max": 40.0})

    async def go() -> None:
        async with app_in_process(tmp_path / "rec", config=cfg, max_speedup=CAPPED_SPEEDUP,
                                  idle_speedup=IDLE_SPEEDUP) as (m, c):
            assert m.link.rig is not None and m.link.rig.sim is not None and m.link.rig.motor.profile.name == name
            rid = await start(c, freqs=(10.0,), record_s=30.0)
            await wait_state(c, rid, ("running",), "recording")
            m.link.rig.sim.motor.emergency_stop()  # the drive's own quick stop
            st = await wait_state(c, rid, FINAL)
            assert st["state"] == "failed" and "emergency_stop" in st["reason"], st
            r = await c.post("/runs", json=run_body(freqs=(10.0,)))
            assert r.status_code == 409 and "latched" in r.json()["detail"]
            assert (await c.post("/stop/acknowledge", json={"operator": "op"})).status_code == 200
            assert not m.link.rig.sim.motor.snapshot().estop
            rid2 = await start(c, freqs=(10.0,))
            assert (await wait_state(c, rid2))["state"] == "identifying"
    asyncio.run(go())
