"""Redundant measurements check each other, a clock skew is named, and a line is called mains only
at a mains frequency.  Recordings from the project's simulator (``station.simulate``: paper Eq. 3
integrated with the configured truth and effects), never from the code under test."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from station.config import StationConfig, parse_config
from station.discrepancy import analyse_recording
from station.discrepancy.scenarios import scenario_config
from station.ident.identify import identify_recording
from station.recording import read_recording
from station.simulate import simulate_run

_cfg = scenario_config({})
assert _cfg.simulation is not None
KF, BF = _cfg.simulation.truth.k_f, _cfg.simulation.truth.b_f
GAIN = _cfg.displacement_sensor.gain_V_per_m


def _config(effects: dict[str, Any], truth: dict[str, float] | None = None) -> StationConfig:
    d = scenario_config(effects, n_steps=5, record_s=0.6, settle_s=0.2, seed=5).model_dump(exclude_none=True)
    d["simulation"]["truth"].update(truth or {})
    return parse_config(d)


def _checks(path: Path) -> dict[str, Any]:
    res = identify_recording(read_recording(path))
    return {c.name: c for c in res.checks}


@pytest.mark.slow
def test_an_ideal_run_raises_no_redundancy_finding(tmp_path: Path) -> None:
    res = identify_recording(read_recording(simulate_run(_config({}), tmp_path, seed=5)))
    names = {c.name for c in res.checks}
    assert not names & {"displacement_vs_radius", "clock_skew", "model_misfit", "static_force_vs_weight"}, names
    assert "crank radius u = 1e-07 m" in res.assumptions.unsupported_defaults
    assert "measurement chain gain u = 0.0001 (relative)" in res.assumptions.unsupported_defaults


@pytest.mark.slow
def test_a_displacement_channel_reading_half_a_percent_high_is_found(tmp_path: Path) -> None:
    """S comes out 0.5 % low (z -8 on its budget): the finding names the two standards and the defaults."""
    checks = _checks(simulate_run(_config({}, {"displacement_gain_V_per_m": 1.005 * GAIN}), tmp_path, seed=5))
    c = checks["displacement_vs_radius"]
    assert c.severity == "warning" and abs(c.values["ratio"] - 1.005) < 3 * c.values["std"], c.message
    assert "displacement sensor's calibration" in c.message and "crank radius" in c.message
    assert "defaults no certificate supports" in c.message


@pytest.mark.slow
def test_the_static_force_disagrees_with_the_weight_when_the_acceleration_scale_is_off(tmp_path: Path) -> None:
    """The displacement channel reads 3 % high: S comes out 3 % low, so the force channel's mean (the
    gravity preload) over S is 1.03 times the weight of the stated masses; the finding says so within
    its stated u and names the displacement sensor first (the radius check agrees)."""
    cfg = _config({}, {"displacement_gain_V_per_m": 1.03 * GAIN})
    d = cfg.model_dump(exclude_none=True)
    d["plan"]["steps"] = d["plan"]["steps"][:3]
    checks = _checks(simulate_run(parse_config(d), tmp_path, seed=5))
    c = checks["static_force_vs_weight"]
    assert c.severity == "warning" and abs(c.values["ratio"] - 1.03) < 3 * c.values["std"], c.message
    assert "displacement sensor's calibration (the acceleration S rests on) first" in c.message, c.message
    assert "standard gravity used, a default no certificate supports" in c.message


def test_the_static_comparison_only_where_the_plan_allows() -> None:
    """A charge amplifier's chain (V/pC) and an imported file have no known zero: no static check."""
    from station.ident.response.redundancy import static_check
    from station.ident.result import Estimate
    S = Estimate(2e-3, 2e-7, "V/N")
    off = ((0.1, -0.6, 1e-5), (0.5, -0.6, 1e-5))  # 16 % above the weight of 26.3 kg: a finding
    bridge = {"conditioner": {"gain_unit": "V/V", "offset_V": 0.0}}
    assert static_check(off, S, 26.3, bridge, False) is not None
    assert static_check(off, S, 26.3, {"conditioner": {"gain_unit": "V/pC", "offset_V": 0.0}}, False) is None
    assert static_check(off, S, 26.3, {"format": "sinecal-csv"}, False) is None


@pytest.mark.slow
def test_a_clock_skew_between_the_converters_is_named(tmp_path: Path) -> None:
    """The force converter's clock 50 ppm fast: identify names the skew (measured within its u) and
    offers it beside a coupling."""
    res = identify_recording(read_recording(simulate_run(_config({"clock_skew": {"relative": 5e-5}}), tmp_path,
                                                         seed=5)))
    checks = {c.name: c for c in res.checks}
    c = checks["clock_skew"]
    assert abs(c.values["relative"] + 5e-5) < 5e-6, c.message
    coupling = [x for x in res.checks if x.name in ("coupling_suspected", "coupling_not_excluded", "model_misfit")]
    assert coupling and all("clock skew" in x.message for x in coupling)


@pytest.mark.slow
def test_the_model_gap_names_a_clock_skew_and_covers_the_truth(tmp_path: Path) -> None:
    rep = analyse_recording(simulate_run(_config({"clock_skew": {"relative": 5e-5}}), tmp_path, seed=5))
    assert "clock_skew" in [e.name for e in rep.effects], [e.name for e in rep.effects]
    for k, true in (("k_f", KF), ("b_f", BF)):
        e = rep.parameters_after[k]
        assert e.value is not None and e.std is not None, e
        assert e.identifiable and abs(e.value - true) <= 3 * e.std, (k, e)


@pytest.mark.slow
def test_a_lightly_damped_transducer_rings_at_its_own_frequency_not_mains(tmp_path: Path) -> None:
    """Q = 300: the free oscillation at the natural frequency is never named mains (no mains in the data)."""
    rep = analyse_recording(simulate_run(_config({}, {"b_f": 92.0}), tmp_path, seed=5))
    assert "mains_interference" not in [e.name for e in rep.effects]
    assert not any("mains" in u for u in rep.unexplained), rep.unexplained
    assert not rep.mains_search.startswith("line at"), rep.mains_search
    e = rep.parameters_after["b_f"]
    assert e.value is not None and e.std is not None, e
    assert e.identifiable and abs(e.value - 92.0) <= 3 * e.std, e
