"""Unit tests of the register map (declared once in config/motor_registers.yaml)."""

from __future__ import annotations

import copy

import pytest
import yaml

from drivers.motor.errors import MotorValueError, RegisterMapError
from drivers.motor.registers import DEFAULT_REGISTER_MAP_PATH, load_register_map, parse_register_map


@pytest.fixture(scope="module")
def doc() -> dict:
    return yaml.safe_load(DEFAULT_REGISTER_MAP_PATH.read_text())


def test_shipped_map_declares_every_register_with_type_scaling_and_unit() -> None:
    m = load_register_map()
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
    m = load_register_map()
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
    m = load_register_map()
    word = m.encode_status({"enabled": True, "fault": True, "watchdog_expired": True})
    assert word == 0b110001
    flags = m.decode_status(word)
    assert flags["enabled"] and flags["fault"] and not flags["running"]


@pytest.mark.parametrize(("mutate", "message"), [
    (lambda d: d["registers"]["enable"].update(type="float32"), r"registers.enable.type: expected one of"),
    (lambda d: d["registers"]["enable"].update(address=-1), r"registers.enable.address: expected an integer"),
    (lambda d: d["registers"]["enable"].update(scale=0), r"scale: expected a finite non-zero number, got 0"),
    (lambda d: d["registers"]["enable"].update(access="w"), r"access: expected 'r' or 'rw', got 'w'"),
    (lambda d: d["registers"]["enable"].update(colour="red"), r"expected only keys .*got \['colour'\]"),
    (lambda d: d["registers"]["fault_code"].update(address=105), r"address 105 not used twice"),
    (lambda d: d["registers"].pop("watchdog"), r"missing \['watchdog'\]"),
    (lambda d: d["device"].update(max_speed=1), r"device: expected only keys"),
])
def test_malformed_map_names_what_was_expected_and_received(doc: dict, mutate, message: str) -> None:
    bad = copy.deepcopy(doc)
    mutate(bad)
    with pytest.raises(RegisterMapError, match=message):
        parse_register_map(bad, "test.yaml")


def test_not_yaml_is_a_register_map_error(tmp_path) -> None:
    p = tmp_path / "bad.yaml"
    p.write_text("registers: [unclosed")
    with pytest.raises(RegisterMapError, match="not valid YAML"):
        load_register_map(p)
