"""Shared fixtures of the foundation tests: small, fast configurations derived from
config/sim-5kN.yaml and simulated recordings made once per session.

Session-scoped recordings are shared: tests must not modify them (copy them into tmp_path first).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from station.config import StationConfig, default_config_path, parse_config
from station.simulate import simulate_run

REPO = Path(__file__).resolve().parent.parent
CONFIG_DIR = REPO / "config"


def _base_dict() -> dict[str, Any]:
    data = yaml.safe_load(default_config_path().read_text(encoding="utf-8"))
    assert isinstance(data, dict)
    return data


def make_fast_dict(*, one_radius: bool = False) -> dict[str, Any]:
    """config/sim-5kN.yaml with short settle/record/pre-roll times and a fast crank ramp.

    ``one_radius``: every step at the same crank radius (sinecal-csv v1 can only export such runs).
    """
    data = copy.deepcopy(_base_dict())
    data["plan"]["settle_s"] = 0.2
    data["plan"]["record_s"] = 0.5
    data["rig"]["acceleration_hz_per_s"] = 100.0
    data["simulation"]["pre_roll_s"] = 0.2
    if one_radius:
        data["plan"]["steps"] = [{"crank_frequency_hz": f, "crank_radius_m": 0.0004}
                                 for f in (5.0, 20.0, 60.0)]
    else:  # the shipped radii, fewer steps: each radius change stops the crank
        data["plan"]["steps"] = [
            {"crank_frequency_hz": 4.0, "crank_radius_m": 0.01},
            {"crank_frequency_hz": 30.0, "crank_radius_m": 0.001},
            {"crank_frequency_hz": 100.0, "crank_radius_m": 0.00015},
        ]
    return data


def write_yaml(path: Path, data: Any) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


@pytest.fixture
def base_config_dict() -> dict[str, Any]:
    """A fresh, mutable copy of config/sim-5kN.yaml as parsed YAML."""
    return copy.deepcopy(_base_dict())


@pytest.fixture
def fast_config_dict() -> dict[str, Any]:
    return make_fast_dict()


@pytest.fixture
def fast_config() -> StationConfig:
    return parse_config(make_fast_dict(), "fast")


@pytest.fixture
def fast_config_file(tmp_path: Path) -> Path:
    """The fast (multi-radius) configuration as a YAML file."""
    return write_yaml(tmp_path / "fast.yaml", make_fast_dict())


@pytest.fixture
def one_radius_config_file(tmp_path: Path) -> Path:
    return write_yaml(tmp_path / "one-radius.yaml", make_fast_dict(one_radius=True))


@pytest.fixture
def write_config(tmp_path: Path) -> Callable[[dict[str, Any], str], Path]:
    """Write a configuration mapping as YAML into tmp_path; returns the file's path."""

    def write(data: dict[str, Any], name: str = "station.yaml") -> Path:
        return write_yaml(tmp_path / name, data)

    return write


@pytest.fixture(scope="session")
def sim_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A completed simulated recording of the fast multi-radius plan (read-only: do not modify)."""
    out = tmp_path_factory.mktemp("sim")
    return simulate_run(parse_config(make_fast_dict(), "fast"), out)


@pytest.fixture(scope="session")
def sim_recording_one_radius(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A completed simulated recording with a single crank radius (read-only: do not modify)."""
    out = tmp_path_factory.mktemp("sim1r")
    return simulate_run(parse_config(make_fast_dict(one_radius=True), "fast-1r"), out, seed=7)
