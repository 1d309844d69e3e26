"""Station configuration: strict pydantic models behind config/*.yaml, and the rig limits derived
from them.  Refusals must name the file, the key, the value received and the allowed range."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pydantic
import pytest
import yaml

from station.config import (
    StationConfig,
    StepSpec,
    config_to_yaml,
    default_config_path,
    load_config,
    parse_config,
    to_rig_physics,
)
from station.errors import BadInputError, ConfigError, LimitError
from station.limits import G, check_steps, force_limit_N, peak_force_N


def _step(f: float, r: float) -> StepSpec:
    """A step as asked, its values not yet checked (the limits check them)."""
    return StepSpec.model_construct(crank_frequency_hz=f, crank_radius_m=r)

WriteConfig = Callable[..., Path]
CONFIG_DIR = Path(__file__).resolve().parent.parent / "config"


def _set(data: dict[str, Any], dotted: str, value: Any) -> None:
    """Set ``a.b.0.c`` in nested dicts/lists."""
    *parents, last = dotted.split(".")
    node: Any = data
    for part in parents:
        node = node[int(part)] if isinstance(node, list) else node[part]
    if isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value


def _refusal(write_config: WriteConfig, data: dict[str, Any]) -> tuple[Path, str]:
    path = write_config(data)
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    return path, str(exc.value)


# -- the shipped files ----------------------------------------------------------------------------

@pytest.mark.parametrize("path", sorted(CONFIG_DIR.glob("sim-*.yaml")), ids=lambda p: p.name)
def test_shipped_station_configs_load_with_their_values(path: Path) -> None:
    raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    cfg = load_config(path)
    assert cfg.transducer.id == raw["transducer"]["id"]
    assert cfg.transducer.capacity_N == raw["transducer"]["capacity_N"]
    assert cfg.rig.top_mass_kg == raw["rig"]["top_mass_kg"]
    assert cfg.rig.load_mass_kg == pytest.approx(raw["rig"]["top_mass_kg"] + raw["rig"]["adaption_mass_kg"])
    assert [(s.crank_frequency_hz, s.crank_radius_m) for s in cfg.plan.steps] == [
        (s["crank_frequency_hz"], s["crank_radius_m"]) for s in raw["plan"]["steps"]]
    assert cfg.simulation is not None
    # PyYAML (YAML 1.1) reads an exponent without a sign ("2.91e7") as a string; pydantic parses it
    assert cfg.simulation.truth.k_f == float(raw["simulation"]["truth"]["k_f"])
    # every shipped plan respects the rig limits it declares
    check_steps(cfg, cfg.plan.steps)


def test_default_config_path_is_the_5kN_simulation() -> None:
    # found through the installed data package (in a worktree run that may be another checkout's config/)
    assert default_config_path().name == "sim-5kN.yaml"
    assert load_config(default_config_path()).transducer.capacity_N == 5000


def test_every_config_file_is_shipped() -> None:
    from sinecal_config import config_file

    for p in CONFIG_DIR.glob("*.yaml"):
        assert config_file(p.name).is_file()
    with pytest.raises(FileNotFoundError, match=r"'nope.yaml' is not among .*sim-5kN.yaml"):
        config_file("nope.yaml")


def test_defaults_fill_optional_sections(base_config_dict: dict[str, Any]) -> None:
    for key in ("station", "conditioner", "displacement_sensor", "daq"):
        del base_config_dict[key]
    cfg = parse_config(base_config_dict)
    assert cfg.daq.sample_rate_hz == 20_000.0
    assert cfg.daq.adc_bits == 16
    assert cfg.conditioner.gain == 1000.0
    assert cfg.station.recordings_dir == "recordings"


def test_config_snapshot_yaml_round_trips(base_config_dict: dict[str, Any]) -> None:
    cfg = parse_config(base_config_dict)
    again = parse_config(yaml.safe_load(config_to_yaml(cfg)), "snapshot")
    assert again == cfg


def test_models_are_frozen(base_config_dict: dict[str, Any]) -> None:
    cfg = parse_config(base_config_dict)
    with pytest.raises(pydantic.ValidationError):
        cfg.rig.top_mass_kg = 1.0  # type: ignore[misc]


# -- unknown keys ---------------------------------------------------------------------------------

@pytest.mark.parametrize(("where", "key"), [
    ("", "stations"),
    ("rig", "top_mass"),
    ("rig.crank_radius_m", "mid"),
    ("plan.steps.2", "record_time"),
    ("simulation.effects", "thermal_drift"),
])
def test_unknown_key_is_refused_naming_it(write_config: WriteConfig, base_config_dict: dict[str, Any],
                                          where: str, key: str) -> None:
    node: Any = base_config_dict
    for part in where.split(".") if where else []:
        node = node[int(part)] if isinstance(node, list) else node[part]
    node[key] = 1234.5
    path, msg = _refusal(write_config, base_config_dict)
    dotted = f"{where}.{key}" if where else key
    assert str(path) in msg
    assert f"{dotted}: unknown key" in msg
    assert "1234.5" in msg


# -- out-of-range values --------------------------------------------------------------------------

@pytest.mark.parametrize(("key", "value", "allowed"), [
    ("rig.top_mass_kg", 0, "> 0 and <= 500"),
    ("rig.top_mass_kg", 501.0, "> 0 and <= 500"),
    ("rig.peak_force_fraction", 1.5, "> 0 and <= 1.0"),
    ("rig.crank_radius_m.min", -0.001, ">= 0"),
    ("transducer.capacity_N", -5000, "> 0 and <= 10000000.0"),
    ("transducer.sensitivity_V_per_N", 2.0, "> 0 and <= 1.0"),
    ("transducer.end_mass_kg", -0.1, "> 0 and <= 100"),
    ("conditioner.offset_V", 12.0, ">= -10 and <= 10"),
    ("daq.sample_rate_hz", 500, ">= 1000 and <= 200000"),
    ("daq.adc_bits", 24, ">= 8 and <= 16"),
    ("plan.record_s", 0, "> 0 and <= 3600"),
    ("plan.steps.3.crank_frequency_hz", -60.0, "> 0 and <= 1000"),
    ("plan.steps.0.crank_radius_m", 2.0, "> 0 and <= 1.0"),
    ("simulation.truth.b_f", -1.0, ">= 0 and <= 100000000.0"),
    ("simulation.seed", -3, ">= 0"),
])
def test_out_of_range_value_names_key_value_and_range(write_config: WriteConfig,
                                                      base_config_dict: dict[str, Any],
                                                      key: str, value: float, allowed: str) -> None:
    _set(base_config_dict, key, value)
    path, msg = _refusal(write_config, base_config_dict)
    assert str(path) in msg
    assert f"{key} = {value!r}:" in msg
    assert f"allowed: value {allowed}" in msg


@pytest.mark.parametrize(("key", "text"), [
    ("rig.crank_radius_m.max", ".inf"),          # no upper bound would catch it: disables the limit check
    ("rig.crank_frequency_hz.max", ".inf"),
    ("rig.top_mass_kg", ".nan"),
    ("simulation.effects.mains_interference.amplitudes_V.0", ".nan"),
])
def test_inf_and_nan_are_refused(tmp_path: Path, base_config_dict: dict[str, Any], key: str,
                                 text: str) -> None:
    base_config_dict["simulation"]["effects"]["mains_interference"] = {"amplitudes_V": [0.01]}
    _set(base_config_dict, key, "PLACEHOLDER")
    path = tmp_path / "station.yaml"
    path.write_text(yaml.safe_dump(base_config_dict).replace("PLACEHOLDER", text), encoding="utf-8")
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert f"{key} = " in str(exc.value)
    assert "finite" in str(exc.value)


def test_wrong_type_names_key_and_value(write_config: WriteConfig, base_config_dict: dict[str, Any]) -> None:
    base_config_dict["rig"]["top_mass_kg"] = "heavy"
    _, msg = _refusal(write_config, base_config_dict)
    assert "rig.top_mass_kg = 'heavy'" in msg
    assert "valid number" in msg
    assert "allowed: value > 0 and <= 500" in msg


def test_range_with_min_above_max_is_refused(write_config: WriteConfig,
                                             base_config_dict: dict[str, Any]) -> None:
    base_config_dict["rig"]["crank_frequency_hz"] = {"min": 50.0, "max": 20.0}
    _, msg = _refusal(write_config, base_config_dict)
    assert "rig.crank_frequency_hz" in msg
    assert "min (50.0) must not exceed max (20.0)" in msg


def test_bad_transducer_id_is_refused(write_config: WriteConfig, base_config_dict: dict[str, Any]) -> None:
    base_config_dict["transducer"]["id"] = "TX 5K/1"  # would end up in file names
    _, msg = _refusal(write_config, base_config_dict)
    assert "transducer.id = 'TX 5K/1'" in msg
    assert "pattern" in msg


def test_missing_required_key_is_named(write_config: WriteConfig, base_config_dict: dict[str, Any]) -> None:
    del base_config_dict["simulation"]["truth"]["k_f"]
    _, msg = _refusal(write_config, base_config_dict)
    assert "simulation.truth.k_f: required key is missing" in msg


def test_empty_plan_is_refused(write_config: WriteConfig, base_config_dict: dict[str, Any]) -> None:
    base_config_dict["plan"]["steps"] = []
    _, msg = _refusal(write_config, base_config_dict)
    assert "plan.steps = []" in msg
    assert "at least 1 item" in msg


def test_every_problem_is_listed(write_config: WriteConfig, base_config_dict: dict[str, Any]) -> None:
    base_config_dict["rig"]["top_mass_kg"] = -1
    base_config_dict["daq"]["adc_bits"] = 4
    base_config_dict["conditioner"]["colour"] = "red"
    _, msg = _refusal(write_config, base_config_dict)
    assert "rig.top_mass_kg = -1" in msg
    assert "daq.adc_bits = 4" in msg
    assert "conditioner.colour: unknown key" in msg


# -- files that are not configurations ------------------------------------------------------------

def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError, match="cannot read configuration") as exc:
        load_config(path)
    assert str(path) in str(exc.value)


def test_invalid_yaml(tmp_path: Path) -> None:
    path = tmp_path / "broken.yaml"
    path.write_text("rig: {top_mass_kg: [1, 2\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="not valid YAML") as exc:
        load_config(path)
    assert str(path) in str(exc.value)


@pytest.mark.parametrize(("text", "kind"), [("", "NoneType"), ("- 1\n- 2\n", "list"), ("42\n", "int")])
def test_top_level_must_be_a_mapping(tmp_path: Path, text: str, kind: str) -> None:
    path = tmp_path / "odd.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match=f"expected a mapping at the top level, got {kind}"):
        load_config(path)


def test_config_error_is_bad_input() -> None:
    assert issubclass(ConfigError, BadInputError)
    assert ConfigError.exit_code == 2


# -- conversion to the simulator's physics --------------------------------------------------------

def test_rig_physics_from_config(base_config_dict: dict[str, Any]) -> None:
    cfg = parse_config(base_config_dict)
    ph = to_rig_physics(cfg)
    assert ph.transducer.k_f == 2.91e7
    assert ph.transducer.b_f == 17136.0
    assert ph.transducer.m_l == pytest.approx(25.717 + 0.45)
    assert ph.transducer.m_e == 0.12  # from the transducer section
    assert ph.transducer.sensitivity_V_per_N == 2.0e-6
    assert ph.conditioner.gain == 1000.0
    assert ph.sample_rate_hz == 20_000.0
    assert ph.effects.active() == []


def test_rig_physics_truth_overrides_nominal(base_config_dict: dict[str, Any]) -> None:
    base_config_dict["simulation"]["truth"].update(end_mass_kg=0.2, sensitivity_V_per_N=2.1e-6)
    base_config_dict["simulation"]["effects"] = {"channel_delay": {"delay_s": 1e-5},
                                                 "mains_interference": {"amplitudes_V": [0.01, 0.002]}}
    ph = to_rig_physics(parse_config(base_config_dict))
    assert ph.transducer.m_e == 0.2
    assert ph.transducer.sensitivity_V_per_N == 2.1e-6
    assert ph.effects.active() == ["channel_delay", "mains_interference"]
    assert ph.effects.mains_interference is not None
    assert ph.effects.mains_interference.amplitudes_V == (0.01, 0.002)


def test_rig_physics_needs_simulation_section(base_config_dict: dict[str, Any]) -> None:
    del base_config_dict["simulation"]
    with pytest.raises(ConfigError, match="no 'simulation' section"):
        to_rig_physics(parse_config(base_config_dict))


def test_rig_physics_needs_an_end_mass(base_config_dict: dict[str, Any]) -> None:
    del base_config_dict["transducer"]["end_mass_kg"]
    with pytest.raises(ConfigError, match="end mass"):
        to_rig_physics(parse_config(base_config_dict))


# -- rig limits -----------------------------------------------------------------------------------

@pytest.fixture
def cfg5k(base_config_dict: dict[str, Any]) -> StationConfig:
    return parse_config(base_config_dict)


def test_peak_force_includes_gravity_and_end_mass(cfg5k: StationConfig) -> None:
    m = 25.717 + 0.45 + 0.12
    w = 2 * math.pi * 30.0
    assert peak_force_N(cfg5k, _step(30.0, 0.001)) == pytest.approx(m * (G + 0.001 * w * w))
    assert peak_force_N(cfg5k, _step(1.0, 0.0)) == pytest.approx(m * G)  # the static preload
    assert force_limit_N(cfg5k) == pytest.approx(0.8 * 5000)


@pytest.mark.parametrize(("freq", "radius", "fragment"), [
    (0.5, 0.001, "crank frequency 0.5 Hz is outside the rig's range [1, 100] Hz"),
    (120.0, 0.0001, "crank frequency 120 Hz is outside the rig's range [1, 100] Hz"),
    (10.0, 0.06, "crank radius 0.06 m is outside the rig's range [0.0001, 0.05] m"),
    (10.0, 5e-5, "crank radius 5e-05 m is outside the rig's range"),
    (float("nan"), 0.001, "crank frequency nan Hz is outside"),
    (100.0, 0.001, "peak force"),
])
def test_limits_refuse_the_step_and_name_it(cfg5k: StationConfig, freq: float, radius: float,
                                            fragment: str) -> None:
    steps = [_step(4.0, 0.01), _step(freq, radius)]
    with pytest.raises(LimitError) as exc:
        check_steps(cfg5k, steps)
    assert str(exc.value).startswith(f"step 2 ({freq:g} Hz, {radius:g} m)")  # counted from 1
    assert fragment in str(exc.value)


def test_force_limit_message_gives_the_largest_radius(cfg5k: StationConfig) -> None:
    with pytest.raises(LimitError) as exc:
        check_steps(cfg5k, [_step(100.0, 0.001)])
    msg = str(exc.value)
    assert "exceeds the limit 4000 N (0.8 x capacity 5000 N)" in msg
    r_max = float(msg.rsplit("below ", 1)[1].split(" m")[0])
    # the radius named is (to 3 digits) the one at which the peak force reaches the limit
    assert peak_force_N(cfg5k, _step(100.0, r_max)) == pytest.approx(4000.0, rel=2e-3)
    check_steps(cfg5k, [_step(100.0, r_max * 0.99)])


def test_limits_need_a_step(cfg5k: StationConfig) -> None:
    with pytest.raises(LimitError, match="at least one step"):
        check_steps(cfg5k, [])


def test_every_step_type_has_the_one_declaration_of_a_steps_bounds() -> None:
    """The configuration's plan and the run request (the API's body) share one step type, and the
    interchange file's step refuses the same crank frequency and radius: their bounds come from one
    declaration."""
    from station.config import MAX_CRANK_FREQUENCY_HZ, MAX_CRANK_RADIUS_M, PlanConfig, StepSpec
    from station.interchange import CsvStep
    from station.run.request import RunRequest

    assert RunRequest.model_fields["steps"].annotation == PlanConfig.model_fields["steps"].annotation == list[StepSpec]
    for model, extra in ((StepSpec, {}), (CsvStep, {"file": "a.csv"})):
        ok = {"crank_frequency_hz": MAX_CRANK_FREQUENCY_HZ, "crank_radius_m": MAX_CRANK_RADIUS_M, **extra}
        model.model_validate(ok)
        for key, bad in (("crank_frequency_hz", MAX_CRANK_FREQUENCY_HZ * 1.001), ("crank_frequency_hz", 0.0),
                         ("crank_radius_m", MAX_CRANK_RADIUS_M * 1.001)):
            with pytest.raises(pydantic.ValidationError, match=key):
                model.model_validate({**ok, key: bad})
