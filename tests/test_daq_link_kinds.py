"""DAQ link kinds (a UART bounded by its baud rate, a USB-CDC port bounded by what the bridge reports)
and what the bridge reports of itself at connect (``HW?``, ``rate_exact``): docs/daq-protocol.md."""

from __future__ import annotations

import copy
from collections.abc import Iterator

import pytest
import yaml
from sinecal_config import config_file

from drivers.daq import DaqBridge, DaqCommandError, DaqLinkBudgetError, SerialLink, usb_link_budget
from drivers.daq.bridge import parse_hardware
from drivers.sim.clock import VirtualClock
from drivers.sim.daq_emulator import DaqEmulator
from drivers.sim.daq_inprocess import ClockedDaqLink
from station.config import parse_config
from station.errors import ConfigError
from tests.daq_support import CounterSource, emulator_on_pty


def inprocess(**emu: object) -> tuple[DaqEmulator, DaqBridge]:
    e = DaqEmulator(None, CounterSource(), lambda t: 0.0, clock=VirtualClock(), **emu).start()  # type: ignore[arg-type]
    daq = DaqBridge()
    daq.connect(ClockedDaqLink(e))
    return e, daq


def test_the_bridge_reports_its_hardware_at_connect() -> None:
    _, daq = inprocess(link="usb-cdc", link_bytes_per_s=800_000.0, adc_clock_hz=8_192_000.0)
    try:
        hw = daq.hardware
        assert hw is not None
        assert (hw.identity, hw.adc, hw.adc_bits, hw.channels) == (
            "SINECAL,DAQ-BRIDGE-EMU,SN0001,1.0", "EMULATED", 16, ("disp", "force"))
        assert (hw.adc_clock_hz, hw.link, hw.link_bytes_per_s) == (8_192_000.0, "usb-cdc", 800_000.0)
        assert hw.as_attrs()["daq_link"] == "usb-cdc" and hw.as_attrs()["daq_adc_bits"] == 16
    finally:
        daq.close()


def test_hw_reply_is_checked() -> None:
    ok = "OK HW adc=ADS131M02 bits=24 channels=disp,force clock_hz=8192000 rate_min=250 rate_max=32000 link=uart"
    hw = parse_hardware("X,Y,Z,1", ok)
    assert hw.adc == "ADS131M02" and hw.adc_bits == 24 and hw.link_bytes_per_s is None
    with pytest.raises(DaqCommandError, match="usb-cdc without a positive link_bytes_per_s"):
        parse_hardware("X", ok.replace("link=uart", "link=usb-cdc"))
    with pytest.raises(DaqCommandError, match=r"link='spi' \(expected uart or usb-cdc\)"):
        parse_hardware("X", ok.replace("link=uart", "link=spi"))
    with pytest.raises(DaqCommandError, match="expected adc=, bits="):
        parse_hardware("X", ok.replace(" bits=24", ""))


def test_the_recorded_rate_is_the_one_the_adc_delivers() -> None:
    """An ADC clocked at 8.192 MHz divides by a whole number: 20 kHz asked is 8.192 MHz / 410."""
    _, daq = inprocess(adc_clock_hz=8_192_000.0)
    try:
        cfg = daq.configure(rate_hz=20_000, frame_samples=256)
        assert cfg.rate_requested_hz == 20_000.0
        assert cfg.rate_hz == pytest.approx(8_192_000.0 / 410, rel=1e-9) and cfg.rate_hz != 20_000.0
        assert daq.status()["rate_exact"] == f"{8_192_000.0 / 410:.10g}"
        # a rate the clock cannot come within 1 % of is refused by the bridge
        with pytest.raises(DaqCommandError, match="ERR 2 bad value for rate"):
            daq.configure(rate_hz=1_000_000, frame_samples=256, check_link_budget=False)
    finally:
        daq.close()


@pytest.fixture
def usb_bridge() -> Iterator[tuple[DaqEmulator, str]]:
    with emulator_on_pty(crank_hz=0.0, link="usb-cdc", link_bytes_per_s=200_000.0) as bridge:
        yield bridge


def test_usb_cdc_budget_is_the_bridges_throughput_not_the_baud_rate(usb_bridge: tuple[DaqEmulator, str]) -> None:
    _, path = usb_bridge
    # 20 kHz needs 20000/256 x 2072 = 161,875 B/s in the worst case: 200,000 B/s carry it, and the
    # 9600 Bd the port was opened with do not matter on a CDC port
    daq = DaqBridge()
    daq.connect(SerialLink(path, baudrate=9600, kind="usb-cdc"))
    try:
        assert daq.configure(rate_hz=20_000).rate_hz == 20_000.0
        with pytest.raises(DaqLinkBudgetError, match=r"sustaining 200,000 B/s .* cannot carry 30000 Hz .* "
                                                     r"expected at least 242,812 B/s"):
            daq.configure(rate_hz=30_000)
    finally:
        daq.close()
    # the same port taken for a UART: the kinds disagree, refused before anything is configured
    daq = DaqBridge()
    daq.connect(SerialLink(path, baudrate=3_000_000, kind="uart"))
    try:
        with pytest.raises(DaqLinkBudgetError, match="configured for uart, the bridge reports link=usb-cdc"):
            daq.configure(rate_hz=20_000)
    finally:
        daq.close()
    assert usb_link_budget(20_000, 161_875).margin == pytest.approx(1.0)


def test_config_link_kind() -> None:
    base = yaml.safe_load(config_file("sim-5kN.yaml").read_text(encoding="utf-8"))

    def cfg(link: str, baud: int) -> object:
        d = copy.deepcopy(base)
        d.setdefault("devices", {}).update({"daq_link": link, "daq_baudrate": baud})
        return parse_config(d, "test.yaml")

    cfg("usb-cdc", 9600)  # the baud rate of a CDC port is not the budget
    with pytest.raises(ConfigError, match="9600 Bd cannot carry 20000 Hz"):
        cfg("uart", 9600)
    with pytest.raises(ConfigError, match="daq_link"):
        cfg("spi", 3_000_000)


def test_a_run_over_a_usb_cdc_link_records_what_the_bridge_reported(tmp_path) -> None:
    """The simulated rig's bridge is a USB-CDC one when the configuration says so: the run's budget is
    its throughput (the 9600 Bd configured do not matter) and the recording stores the link."""
    import h5py

    from station.run.request import StepSpec
    from tests.run_support import run_with, small_config

    d = small_config(record_s=0.5)
    d.setdefault("devices", {}).update({"daq_link": "usb-cdc", "daq_baudrate": 9600})
    outcome, _, _ = run_with(tmp_path, None, lambda r, p: None, cfg=parse_config(d, "test.yaml"),
                             steps=[StepSpec(crank_frequency_hz=10.0, crank_radius_m=0.001)])
    assert outcome.exit_status == "completed", outcome.reason  # type: ignore[attr-defined]
    with h5py.File(outcome.path, "r") as f:  # type: ignore[attr-defined]
        attrs = f["raw"].attrs
        assert attrs["daq_link"] == "usb-cdc" and attrs["daq_link_bytes_per_s"] == 1_000_000.0


def test_malformed_commands_get_an_untagged_err_4_and_the_bridge_keeps_answering() -> None:
    """A non-ASCII command byte and a bad SLIP escape are malformed packets (ERR 4, untagged); the
    emulator stays up; the asked rate is echoed as asked; frame takes plain digits only."""
    from drivers.daq.protocol import PKT_COMMAND, StreamDecoder, encode_command, encode_packet

    emu = DaqEmulator(None, CounterSource(), lambda t: 0.0, clock=VirtualClock()).start()

    def ask(raw: bytes) -> list[str]:
        emu.feed(raw)
        return [getattr(e, "text", "") for e in StreamDecoder(256).feed(emu.pull(1 << 16))]

    assert ask(encode_packet(PKT_COMMAND, b"#7 IDN\xff")) == ["ERR 4 malformed command packet (not printable ASCII)"]
    assert ask(bytes.fromhex("C010DB41C0")) == ["ERR 4 malformed command packet (SLIP escape)"]
    assert ask(encode_command("IDN?", "#8")) == ["#8 OK SINECAL,DAQ-BRIDGE-EMU,SN0001,1.0"]
    conf = ask(encode_command("CONF rate=12345.67 frame=256", "#9"))[0]
    assert "rate=12345.67 rate_exact=12345.67 " in conf
    assert ask(encode_command("CONF frame=1_6", "#10"))[0].startswith("#10 ERR 2 bad value for frame")
    emu.close()
