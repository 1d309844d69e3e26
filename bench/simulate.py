"""Synthesis speed of the simulated rig: two channels at 20 kHz, coupled model, every effect on.

Prints JSON: ``realtime_factor`` (median over repeats of seconds of signal per second of wall time),
``realtime_factor_cpu`` (the same per second of this process's CPU time: what a loaded machine's
other processes do not change), the same figures with no effects as a baseline measured side by
side, and the load average (``os.getloadavg``) before and after.  The first block of every run
(the ramp) is not timed: it also compiles the kernels or reads them from numba's cache.
"""

from __future__ import annotations

import json
import os
import statistics
import time

from drivers.rig import params as rp
from drivers.rig.presets import paper_5kN_physics
from drivers.rig.synth import RigSynth

ALL_EFFECTS = rp.Effects(
    coupling_compliance=rp.CouplingCompliance(5e8, 400.0),
    conditioner_lowpass=rp.ConditionerLowpass(4, 1000.0),
    channel_delay=rp.ChannelDelay(2.5e-5),
    crank_harmonics=rp.CrankHarmonics(0.25),
    transducer_nonlinearity=rp.TransducerNonlinearity(0.01, 0.002),
    mains_interference=rp.MainsInterference((0.005, 0.001, 0.002), frequency_hz=50.0),
    zero_drift=rp.ZeroDrift(1e-4),
    displacement_resonance=rp.DisplacementResonance(5000.0, 0.05),
)


def measure(effects: rp.Effects, seconds: float = 10.0, repeats: int = 7,
            block_s: float = 1.0) -> tuple[float, float]:
    """Median real-time factors (wall, CPU) of a steady run with one ramp, in blocks of ``block_s``."""
    ph = paper_5kN_physics(effects)
    n = int(ph.sample_rate_hz * block_s)
    factors, cpu = [], []
    for r in range(repeats):
        s = RigSynth(ph, seed=r, crank_radius_m=0.002)
        s.advance(n, 20.0)  # ramp up (not timed: one ramp per step in a real run is rare)
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(int(seconds / block_s)):
            s.advance(n, 20.0)
        factors.append(seconds / (time.perf_counter() - t0))
        cpu.append(seconds / (time.process_time() - c0))
    return statistics.median(factors), statistics.median(cpu)


def main() -> None:
    load_before = os.getloadavg()
    wall, cpu = measure(ALL_EFFECTS)
    wall0, cpu0 = measure(rp.Effects())
    out = {
        "realtime_factor": round(wall, 1),
        "realtime_factor_cpu": round(cpu, 1),
        "realtime_factor_no_effects": round(wall0, 1),
        "realtime_factor_no_effects_cpu": round(cpu0, 1),
        "realtime_factor_all_effects_ramping": round(_ramping(), 1),
        "target_realtime_factor": 1000,
        "effects": ALL_EFFECTS.active(),
        "sample_rate_hz": 20000,
        "channels": 2,
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
    }
    print(json.dumps(out, indent=2))


def _ramping(seconds: float = 10.0) -> float:
    ph = paper_5kN_physics(ALL_EFFECTS)
    s = RigSynth(ph, seed=0, crank_radius_m=0.002)
    n = int(ph.sample_rate_hz)
    s.advance(n, 15.0)  # not timed, as in measure
    t0 = time.perf_counter()
    for k in range(int(seconds)):
        s.advance(n, 10.0 + 5.0 * (k % 2))
    return seconds / (time.perf_counter() - t0)


if __name__ == "__main__":
    main()
