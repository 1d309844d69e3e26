"""Offline simulation: a whole stepped-sine run written straight from the physics as a recording.

The crank follows the motor's speed profile: standstill (pre-roll), a ramp at the configured
acceleration to each step's frequency, settle, record, and a ramp down to standstill at the end.
A change of crank radius between steps stops the crank first, as on the real rig.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from drivers.rig.synth import RigSynth
from station.config import StationConfig, config_to_yaml, to_rig_physics
from station.environment import run_environment
from station.limits import check_steps
from station.recording import ChannelSpec, RecordingWriter, RunMetadata, new_run_id

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Segment:
    """Crank frequency moves linearly to ``f_end_hz`` over ``n`` samples; ``record`` marks a step's
    record window (its index), radius changes happen before a segment at standstill."""

    n: int
    f_end_hz: float
    radius_m: float
    record: int | None = None


def schedule(cfg: StationConfig) -> list[Segment]:
    """The motor's speed profile for the configured plan, as segments of samples."""
    fs = cfg.daq.sample_rate_hz
    acc = cfg.rig.acceleration_hz_per_s
    segs: list[Segment] = []
    f = 0.0
    radius = cfg.plan.steps[0].crank_radius_m
    pre = round((cfg.simulation.pre_roll_s if cfg.simulation else 0.5) * fs)
    if pre:
        segs.append(Segment(pre, 0.0, radius))

    def ramp(to: float) -> None:
        nonlocal f
        n = round(abs(to - f) / acc * fs)
        if n:
            segs.append(Segment(n, to, radius))
        f = to

    for i, st in enumerate(cfg.plan.steps):
        if st.crank_radius_m != radius:
            ramp(0.0)
            radius = st.crank_radius_m
        ramp(st.crank_frequency_hz)
        settle = st.settle_s if st.settle_s is not None else cfg.plan.settle_s
        record = st.record_s if st.record_s is not None else cfg.plan.record_s
        if settle:
            segs.append(Segment(round(settle * fs), f, radius))
        segs.append(Segment(round(record * fs), f, radius, record=i))
    ramp(0.0)
    segs.append(Segment(round(0.1 * fs), 0.0, radius))
    return segs


def simulate_run(cfg: StationConfig, out_dir: str | Path, seed: int | None = None,
                 block: int = 20_000) -> Path:
    """Write a recording of the configured plan from the physics; returns its path."""
    check_steps(cfg, cfg.plan.steps)
    physics = to_rig_physics(cfg)
    assert cfg.simulation is not None
    seed = cfg.simulation.seed if seed is None else seed
    segs = schedule(cfg)
    synth = RigSynth(physics, seed=seed, crank_radius_m=segs[0].radius_m)
    adc = physics.adc
    v_d, v_f = adc.volts_per_count(adc.displacement_range_V), adc.volts_per_count(adc.force_range_V)
    gain = cfg.displacement_sensor.gain_V_per_m  # the stated gain (the true one may differ: simulation.truth)
    channels = (
        ChannelSpec("displacement", "i2", "count", "m", scale=v_d / gain, volts_per_count=v_d),
        ChannelSpec("force", "i2", "count", "V", scale=v_f, volts_per_count=v_f),
    )
    meta = RunMetadata(
        run_id=new_run_id(cfg.transducer.id), transducer_id=cfg.transducer.id, source="simulate",
        sample_rate_hz=cfg.daq.sample_rate_hz, load_mass_kg=cfg.rig.load_mass_kg,
        end_mass_kg=cfg.transducer.end_mass_kg,
        sensitivity_V_per_N=cfg.transducer.sensitivity_V_per_N * cfg.conditioner.gain,
        capacity_N=cfg.transducer.capacity_N, config_yaml=config_to_yaml(cfg),
        environment=run_environment(cfg, seed))
    plan = {"kind": "stepped_sine", "seed": seed,
            "steps": [s.model_dump(exclude_none=True) for s in cfg.plan.steps]}
    writer = RecordingWriter(out_dir, meta, channels, plan=plan)
    clipped = 0
    try:
        for seg in segs:
            if seg.radius_m != synth.crank_radius_m:
                synth.set_crank_radius(seg.radius_m)
            start = synth.sample_index
            left = seg.n
            f_start = synth.crank_frequency_hz
            while left:
                n = min(block, left)
                done = seg.n - left + n
                # exact at the segment's end (a float ramp must land on 0 Hz for a radius change)
                f_end = seg.f_end_hz if done == seg.n else f_start + (seg.f_end_hz - f_start) * done / seg.n
                b = synth.advance(n, f_end)
                clipped += b.clipped
                writer.append(b.displacement_counts, b.force_counts)
                left -= n
            if seg.record is not None:
                writer.add_step(crank_frequency_hz=seg.f_end_hz, crank_radius_m=seg.radius_m,
                                start_sample=start, end_sample=start + seg.n)
        if clipped:
            writer.document("event", {"warning": f"{clipped} samples clipped at the ADC range"})
        return writer.finish("completed")
    except BaseException as exc:
        writer.finish("failed", reason=f"simulation failed: {exc!r}")
        raise
