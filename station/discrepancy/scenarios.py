"""Simulated recordings with catalogue effects drawn at random from plausible ranges (for the tests
and the bench).  Every draw is seeded; ranges are those of real rigs, not tuned to the workflow:

* coupling_compliance: k_c in [1, 3] k_f (log-uniform), b_c in [0, 0.5] b_f (a stiffer coupling is, below
  100 Hz, as well described by a delay or a first-order low-pass: the workflow reports such ties);
* conditioner_lowpass: order 1-4, cut-off in [150, 500] Hz (log-uniform; far above the top step a
  low-pass is a pure delay to the data, see docs/discrepancy.md);
* channel_delay: |delay| in [5, 100] us (log-uniform), either sign, a negative one at most 45 us (the
  skew of a multiplexed ADC: the force sampled at most one sample interval, 50 us, before the
  displacement; ``physical``);
* crank_harmonics: connecting rod L in [0.05, 0.5] m (log-uniform);
* transducer_nonlinearity: |quadratic| in [2e-4, 3e-3], |cubic| in [0, 2e-3], either sign;
* mains_interference: 50 or 60 Hz, 1-3 harmonics of 0.2-3 mV, random phases;
* zero_drift: |rate| in [2e-5, 5e-4] V/s, |quadratic| in [0, 2e-5] V/s^2, either sign;
* displacement_resonance: the displacement sensor's own resonance in [300, 1000] Hz (log-uniform),
  damping ratio in [0.3, 1].
"""

from __future__ import annotations

import copy
import functools
import math
from pathlib import Path
from typing import Any

import numpy as np
from sinecal_config import config_file

from drivers.rig.model import spring_force_per_acceleration
from station.config import StationConfig, load_config, parse_config, to_rig_physics
from station.limits import moving_mass_kg
from station.simulate import simulate_run

CONFIGS = {"5kN": "sim-5kN.yaml", "12k5N": "sim-12k5N.yaml"}


def _logu(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _sign(rng: np.random.Generator) -> float:
    return 1.0 if rng.random() < 0.5 else -1.0


def _skew(delay_s: float) -> float:
    """A delay as a multiplexed ADC makes it: a negative one (force first) at most 45 us."""
    return max(delay_s, -45e-6)


def draw_effect(name: str, rng: np.random.Generator, k_f: float, b_f: float) -> dict[str, Any]:
    """Configuration (``simulation.effects.<name>``) of one effect drawn from its plausible range."""
    if name == "coupling_compliance":
        return {"k_c": _logu(rng, 1.0, 3.0) * k_f, "b_c": float(rng.uniform(0, 0.5)) * b_f}
    if name == "conditioner_lowpass":
        return {"order": int(rng.integers(1, 5)), "cutoff_hz": _logu(rng, 150.0, 500.0)}
    if name == "channel_delay":
        return {"delay_s": _skew(_sign(rng) * _logu(rng, 5e-6, 1e-4))}
    if name == "crank_harmonics":
        return {"rod_length_m": _logu(rng, 0.05, 0.5)}
    if name == "transducer_nonlinearity":
        return {"quadratic": _sign(rng) * float(rng.uniform(2e-4, 3e-3)),
                "cubic": _sign(rng) * float(rng.uniform(0.0, 2e-3))}
    if name == "mains_interference":
        n = int(rng.integers(1, 4))
        return {"frequency_hz": float(rng.choice([50.0, 60.0])),
                "amplitudes_V": [float(rng.uniform(2e-4, 3e-3)) for _ in range(n)],
                "phases_rad": [float(rng.uniform(-math.pi, math.pi)) for _ in range(n)]}
    if name == "zero_drift":
        return {"rate_V_per_s": _sign(rng) * _logu(rng, 2e-5, 5e-4),
                "quadratic_V_per_s2": _sign(rng) * float(rng.uniform(0.0, 2e-5))}
    if name == "displacement_resonance":
        return {"resonance_hz": _logu(rng, 300.0, 1000.0), "damping": float(rng.uniform(0.3, 1.0))}
    if name == "clock_skew":
        return {"relative": _sign(rng) * _logu(rng, 1e-5, 1e-4)}
    raise KeyError(name)


WIDE_EFFECTS = ("coupling_compliance", "conditioner_lowpass", "channel_delay")


def draw_wide(name: str, rng: np.random.Generator, k_f: float, b_f: float) -> dict[str, Any]:
    """A fundamental-only effect drawn from ranges wider than those where the data decide: coupling
    k_c in [1, 10] k_f (log-uniform), b_c in [0, 0.5] b_f; low-pass order 1-4, cut-off in [150, 3000] Hz
    (log-uniform); delay |delay| in [1, 100] us (log-uniform), either sign (a negative one at most
    45 us).  The workflow must report ties and undetectable effects as such, never a k_f or b_f off by
    more than 3 stated uncertainties."""
    if name == "coupling_compliance":
        return {"k_c": _logu(rng, 1.0, 10.0) * k_f, "b_c": float(rng.uniform(0, 0.5)) * b_f}
    if name == "conditioner_lowpass":
        return {"order": int(rng.integers(1, 5)), "cutoff_hz": _logu(rng, 150.0, 3000.0)}
    if name == "channel_delay":
        return {"delay_s": _skew(_sign(rng) * _logu(rng, 1e-6, 1e-4))}
    raise KeyError(f"{name} is not a fundamental-only effect ({', '.join(WIDE_EFFECTS)})")


def plan_steps(cfg: StationConfig, n_steps: int, f_lo: float = 5.0, f_hi: float = 95.0,
               fill: float = 0.6) -> list[dict[str, float]]:
    """n steps log-spaced in [f_lo, f_hi] Hz at one crank radius, chosen so that the dynamic spring
    force, with the true transducer's (and coupling's, if simulated) resonance amplification
    |k_f Z2 / (M s^2 X_b)|, uses at most ``fill`` of the rig's peak-force margin
    (M (g + r w^2) <= peak_force_fraction * capacity).
    (One radius: a radius change stops the crank, which ``station.simulate`` does not always reach
    exactly.)"""
    M = moving_mass_kg(cfg)
    a_max = cfg.rig.peak_force_fraction * cfg.transducer.capacity_N / M - 9.80665
    phys = to_rig_physics(cfg)
    freqs = np.geomspace(f_lo, f_hi, n_steps)
    amp = np.abs(spring_force_per_acceleration(phys.transducer, phys.effects.coupling_compliance, freqs)) / M
    r = float(np.min(fill * a_max / amp / (2 * math.pi * freqs) ** 2))
    r = float(f"{min(max(r, cfg.rig.crank_radius_m.min), cfg.rig.crank_radius_m.max):.3g}")
    return [{"crank_frequency_hz": round(float(f), 3), "crank_radius_m": r} for f in freqs]


def scenario_config(effects: dict[str, dict[str, Any]], *, transducer: str = "5kN", n_steps: int = 6,
                    record_s: float = 1.0, settle_s: float = 0.3, seed: int = 1,
                    noise: bool = True) -> StationConfig:
    """A simulated-station configuration with the given effects and a short stepped-sine plan
    (``noise=False``: no sensor or conditioner noise, only the ADC's quantisation)."""
    d = _preset(transducer)
    d["rig"]["acceleration_hz_per_s"] = 100.0
    d["simulation"]["effects"] = effects
    with_effects = parse_config(d)
    d["plan"] = {"settle_s": settle_s, "record_s": record_s, "steps": plan_steps(with_effects, n_steps)}
    d["simulation"]["seed"] = seed
    if not noise:
        d["simulation"]["conditioner_noise_V"] = 0.0
        d["simulation"]["displacement_noise_m"] = 0.0
    return parse_config(d)


@functools.cache
def _preset_dump(transducer: str) -> dict[str, Any]:
    """The shipped configuration of a transducer preset as a dict, read once per process."""
    return load_config(config_file(CONFIGS[transducer])).model_dump(exclude_none=True)


def _preset(transducer: str) -> dict[str, Any]:
    """A copy of ``_preset_dump`` to edit."""
    return copy.deepcopy(_preset_dump(transducer))


def draw_scenario(names: list[str], seed: int, transducer: str = "5kN") -> dict[str, dict[str, Any]]:
    """Effects ``names`` with parameters drawn with ``seed``."""
    truth = _preset_dump(transducer)["simulation"]["truth"]
    rng = np.random.default_rng(seed)
    return {n: draw_effect(n, rng, float(truth["k_f"]), float(truth["b_f"])) for n in names}


def simulate_scenario(effects: dict[str, dict[str, Any]], out_dir: str | Path, seed: int, **kw: Any) -> Path:
    """Write a recording of ``scenario_config(effects, **kw)`` with noise seed ``seed``."""
    return simulate_run(scenario_config(effects, seed=seed, **kw), out_dir, seed=seed)
