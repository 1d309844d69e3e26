"""Unit tests of a drive profile's registers (the station's own controller, config/drives/sinecal-crank.yaml)."""

from __future__ import annotations

import copy

import pytest
import yaml

from drivers.motor.errors import MotorValueError, RegisterMapError
from drivers.motor.profile import load_profile, parse_profile, profile_path


@pytest.fixture(scope="module")
def doc() -> dict:
    return yaml.safe_load(profile_path("sinecal-crank").read_text())


def test_shipped_map_declares_every_register_with_type_scaling_and_unit() -> None:
    m = load_profile()
    for name in ("enable", "frequency_setpoint", "acceleration_ramp", "actual_speed", "crank_angle",
                 "status_word", "fault_code", "watchdog", "emergency_stop"):
        assert name in m.registers
    assert (m["frequency_setpoint"].scale, m["frequency_setpoint"].unit) == (0.01, "Hz")
    units = (m["acceleration_ramp"].unit, m["crank_angle"].unit, m["watchdog_timeout"].unit)
    assert units == ("Hz/s", "deg", "s")
    assert not m["actual_speed"].writable and m["enable"].writable
    assert m.span(["actual_speed", "revolution_count"]) == (100, 6)
    assert m.fault_name(1) == "watchdog_expired" and m.fault_code("emergency_stop") == 2


def test_encode_decode_scaling_sign_and_32_bit_word_order() -> None:
    m = load_profile()
    assert m["frequency_setpoint"].encode(20.0) == [2000]
    assert m["frequency_setpoint"].decode([2000]) == pytest.approx(20.0)
    assert m["actual_speed"].encode(-1.5) == [0xFF6A]
    assert m["actual_speed"].decode([0xFF6A]) == pytest.approx(-1.5)
    assert m["revolution_count"].encode(70000) == [0x0001, 0x1170]  # high word first
    assert m["revolution_count"].decode([0x0001, 0x1170]) == 70000
    with pytest.raises(MotorValueError, match=r"outside the uint16 range \[0, 65535\]"):
        m["frequency_setpoint"].encode(700.0)
    with pytest.raises(MotorValueError, match="finite"):
        m["frequency_setpoint"].encode(float("nan"))


def test_status_word_round_trip() -> None:
    m = load_profile()
    word = m.encode_status({"enabled": True, "fault": True, "watchdog_expired": True, "running": False})
    assert word == 0b110001
    flags = m.decode_status(word)
    assert flags["enabled"] and flags["fault"] and not flags["running"]


@pytest.mark.parametrize(("mutate", "message"), [
    (lambda d: d["registers"]["enable"].update(type="float32"), r"registers.enable.type: expected one of"),
    (lambda d: d["registers"]["enable"].update(address=-1),
     r"registers.enable.address: expected a wire address 0..65535 after numbering, got -1"),
    (lambda d: d["registers"]["enable"].update(scale=0), r"scale: expected a finite non-zero number, got 0"),
    (lambda d: d["registers"]["enable"].update(access="w"), r"access: expected 'r' or 'rw', got 'w'"),
    (lambda d: d["registers"]["enable"].update(colour="red"), r"expected only keys .*got \['colour'\]"),
    (lambda d: d["registers"]["fault_code"].update(address=105), r"address 105 not used twice"),
    (lambda d: d["registers"].pop("watchdog"), r"watchdog.refresh: expected 'any_request' or a writable register, "
                                               r"got 'watchdog'"),
    (lambda d: d["device"].update(max_speed=1), r"device: expected only keys"),
    (lambda d: d["device"].update(max_frequency_hz=50.0), r"limits are the min/max of the set-point and ramp "
                                                          r"registers\), got \['max_frequency_hz'\]"),
    (lambda d: d["registers"]["enable"].update(max="one"), r"registers.enable.max: expected a finite number"),
    (lambda d: d["registers"]["enable"].update(min=2, max=1), r"expected min <= max .*got \(2.0, 1.0\)"),
    (lambda d: d["registers"]["frequency_setpoint"].update(max=700.0),
     r"within what uint16 x 0.01 holds \[0, 655.35\], got \(0.0, 700.0\)"),
    (lambda d: d["registers"]["acceleration_ramp"].pop("max"), r"acceleration_ramp.max: expected a declared limit"),
    (lambda d: d["watchdog"].update(timeout_s=0), r"watchdog.timeout_s: expected a time-out > 0 s \(a profile "
                                                  r"whose communication watchdog is off is refused\), got 0"),
    (lambda d: d["watchdog"].update(timeout_s=0.2), r"watchdog.timeout_s: expected at least 0.5 s \(the station "
                                                    r"refreshes the watchdog every 0.2 s\), got 0.2"),
    (lambda d: d["commands"].pop("quick_stop"), r"commands: expected a sequence for each of .*got \"no 'quick_stop'\""),
    (lambda d: d["commands"]["enable"][0].update(register="actual_speed"),
     r"commands.enable\[0\].register: expected a writable 16-bit register"),
    (lambda d: d["status"]["flags"].update(estop={"bit": 16}), r"status.flags.estop.bit: expected 0..15, got 16"),
    (lambda d: d["registers"]["enable"].update(numbering="modicon"), r"registers.enable.address: expected a "
                                                                      r"Modicon reference 40001..105536"),
])
def test_malformed_map_names_what_was_expected_and_received(doc: dict, mutate, message: str) -> None:
    bad = copy.deepcopy(doc)
    mutate(bad)
    with pytest.raises(RegisterMapError, match=message):
        parse_profile(bad, "test.yaml")


def test_not_yaml_is_a_register_map_error(tmp_path) -> None:
    p = tmp_path / "bad.yaml"
    p.write_text("registers: [unclosed")
    with pytest.raises(RegisterMapError, match="not valid YAML"):
        load_profile(p)
    with pytest.raises(RegisterMapError, match=r"drive profile 'no-such-drive': expected a shipped profile \(.*"
                                               r"sinecal-crank.*\) or a .yaml path"):
        load_profile("no-such-drive")


def test_value_ranges_are_declared_next_to_each_register_and_give_the_device_limits() -> None:
    m = load_profile()
    assert m["frequency_setpoint"].valid_range() == (0.0, 100.0)
    assert (m.device.min_frequency_hz, m.device.max_frequency_hz) == (0.0, 100.0)
    assert m["acceleration_ramp"].valid_range() == (0.01, 100.0) and m.device.max_ramp_hz_per_s == 100.0
    assert m["enable"].valid_range() == (0.0, 1.0)
    assert m["watchdog"].valid_range() == (0.0, 65535.0)  # no declared range: the type's
    m["watchdog_timeout"].check(60.0)
    with pytest.raises(MotorValueError, match=r"register 'watchdog_timeout': expected 0..60 s, got 60.5 s"):
        m["watchdog_timeout"].check(60.5)
    with pytest.raises(MotorValueError, match=r"expected 0.01..100 Hz/s, got 0.0 Hz/s"):
        m["acceleration_ramp"].check(0.0)
    with pytest.raises(MotorValueError, match="got nan"):
        m["enable"].check(float("nan"))
