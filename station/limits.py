"""Rig, transducer and drive limits, checked before anything moves.

The drive's limits are those its profile declares (the ranges of its set-point and ramp registers,
``drivers.motor.profile``), read from the profile the configuration names (``rig.motor.profile``):
the number lives there once, and a plan beyond it is refused here rather than by the drive mid-run.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import Protocol

from drivers.motor.profile import DriveProfile, load_profile
from station.config import StationConfig
from station.errors import LimitError

G = 9.80665


class CrankStep(Protocol):
    """What the limits read of a step (``station.config.StepSpec``, the one step type): its crank
    frequency in Hz and crank radius in m, checked here whatever their values (not-a-number too)."""

    @property
    def crank_frequency_hz(self) -> float: ...

    @property
    def crank_radius_m(self) -> float: ...


def moving_mass_kg(cfg: StationConfig) -> float:
    """M in kg: load mass (top mass + adaption) plus the transducer's end mass, if known."""
    return cfg.rig.load_mass_kg + (cfg.transducer.end_mass_kg or 0.0)


def peak_force_N(cfg: StationConfig, step: CrankStep) -> float:
    """Peak transducer force in N: M (g + r w^2).

    The preload of gravity is included: the transducer sees the static weight plus the inertial
    amplitude M r w^2 on the downward stroke.
    """
    w = 2.0 * math.pi * step.crank_frequency_hz
    return moving_mass_kg(cfg) * (G + step.crank_radius_m * w * w)


def max_radius_m(cfg: StationConfig, crank_frequency_hz: float) -> float:
    """Largest crank radius in m whose peak force stays within ``force_limit_N`` (0 if none does)."""
    w = 2.0 * math.pi * crank_frequency_hz
    return max(0.0, (force_limit_N(cfg) / moving_mass_kg(cfg) - G) / (w * w))


def force_limit_N(cfg: StationConfig) -> float:
    """Largest allowed peak force: the configured fraction of the transducer capacity, in N."""
    return cfg.rig.peak_force_fraction * cfg.transducer.capacity_N


@functools.lru_cache(maxsize=16)
def drive_profile(name_or_path: str) -> DriveProfile:
    """The drive profile a configuration names (parsed once per process; it was validated when the
    configuration was loaded)."""
    return load_profile(name_or_path)


def check_drive(cfg: StationConfig, steps: Sequence[CrankStep] = ()) -> None:
    """Refuse (:class:`LimitError`) what the drive profile ``cfg`` names does not declare: the
    configuration's ``rig.acceleration_hz_per_s`` outside the ramp rates its ramp register(s) take (a
    configuration field), then a step's crank frequency outside its set-point range."""
    profile = drive_profile(cfg.rig.motor.profile)
    dev, acc = profile.device, cfg.rig.acceleration_hz_per_s
    # a drive without a ramp parameter keeps its own ramp: nothing is written, nothing to refuse
    if profile.ramp is not None and not dev.min_ramp_hz_per_s <= acc <= dev.max_ramp_hz_per_s:
        regs = ", ".join(profile.ramp.registers)
        raise LimitError(f"rig.acceleration_hz_per_s {acc:g} Hz/s is outside what drive profile "
                         f"{profile.name!r} takes ({dev.min_ramp_hz_per_s:.4g}..{dev.max_ramp_hz_per_s:.4g} Hz/s, "
                         f"register {regs}); change the configuration, nothing was moved",
                         field="rig.acceleration_hz_per_s", value=acc,
                         limit=(dev.min_ramp_hz_per_s, dev.max_ramp_hz_per_s), in_config=True)
    for i, s in enumerate(steps):
        if not dev.min_frequency_hz <= s.crank_frequency_hz <= dev.max_frequency_hz:
            raise LimitError(f"{_where(i, s)}: crank frequency {s.crank_frequency_hz:g} Hz is outside what drive "
                             f"profile {profile.name!r} can be set to ({dev.min_frequency_hz:g}.."
                             f"{dev.max_frequency_hz:g} Hz, register {profile.setpoint})", step=i,
                             field="crank_frequency_hz", value=s.crank_frequency_hz,
                             limit=(dev.min_frequency_hz, dev.max_frequency_hz))


def _where(i: int, s: CrankStep) -> str:
    return f"step {i + 1} ({s.crank_frequency_hz:g} Hz, {s.crank_radius_m:g} m)"  # people count from 1


def check_steps(cfg: StationConfig, steps: Sequence[CrankStep]) -> None:
    """Refuse the whole run at the first step that breaks a limit: a :class:`LimitError` naming the
    step, the field to change, its value and the limit (a peak force beyond the limit names the
    radius, and the largest radius allowed at that frequency).  What the drive takes is
    :func:`check_drive`'s."""
    if not steps:
        raise LimitError("a run needs at least one step", field="steps", value=0, limit=1)
    fr, rr = cfg.rig.crank_frequency_hz, cfg.rig.crank_radius_m
    limit = force_limit_N(cfg)
    for i, s in enumerate(steps):
        where = _where(i, s)
        if not (math.isfinite(s.crank_frequency_hz) and fr.contains(s.crank_frequency_hz)):
            raise LimitError(f"{where}: crank frequency {s.crank_frequency_hz:g} Hz is outside the rig's "
                             f"range [{fr.min:g}, {fr.max:g}] Hz", step=i, field="crank_frequency_hz",
                             value=s.crank_frequency_hz, limit=(fr.min, fr.max))
        if not (math.isfinite(s.crank_radius_m) and rr.contains(s.crank_radius_m)):
            raise LimitError(f"{where}: crank radius {s.crank_radius_m:g} m is outside the rig's "
                             f"range [{rr.min:g}, {rr.max:g}] m", step=i, field="crank_radius_m",
                             value=s.crank_radius_m, limit=(rr.min, rr.max))
        peak = peak_force_N(cfg, s)
        if peak > limit:
            r_max = max_radius_m(cfg, s.crank_frequency_hz)
            raise LimitError(f"{where}: peak force {peak:.0f} N exceeds the limit {limit:.0f} N "
                             f"({cfg.rig.peak_force_fraction:g} x capacity {cfg.transducer.capacity_N:g} N); "
                             f"at this frequency the radius must stay below {r_max:.3g} m",
                             step=i, field="crank_radius_m", value=s.crank_radius_m, limit=r_max)
