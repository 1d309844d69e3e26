"""Synthesis speed of the simulated rig: two channels at 20 kHz, coupled model, every effect on.

Prints JSON: ``realtime_factor`` (median over repeats of seconds of signal per second of wall time),
``realtime_factor_cpu`` (the same per second of this process's CPU time: what a loaded machine's
other processes change least), each beside the same figure for the staged synthesis
(``RigSynth.advance_stages``: the synthesis as it was before the one-pass kernel, but for its noise
drawn from the same compiled counter-based streams; the same samples to the bit) measured in the
same run, interleaved repeat by repeat; the same with no effects, with a ramping crank, and in the
DAQ emulator's blocks of 256 samples; and the load average (``os.getloadavg``) before and after.
The first block of every run (the ramp) is not timed: it also compiles the kernels or reads them
from numba's cache.

One BLAS thread, as the station's processes run the synthesis (``station.cli``, ``station.blas_env``;
a value the user set is kept): with OpenBLAS's default pool, its worker thread spins for a while after
each synthesiser's set-up (the discretisation's eigenvalues, solves and matrix products) and that
spinning, on the other core, was measured as synthesis: half the CPU time of a run on 2 cores.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # before numpy is imported

import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

from drivers.rig import params as rp  # noqa: E402
from drivers.rig.presets import paper_5kN_physics  # noqa: E402
from drivers.rig.synth import RigSynth  # noqa: E402

ALL_EFFECTS = rp.Effects(
    coupling_compliance=rp.CouplingCompliance(5e8, 400.0),
    conditioner_lowpass=rp.ConditionerLowpass(4, 1000.0),
    channel_delay=rp.ChannelDelay(2.5e-5),
    crank_harmonics=rp.CrankHarmonics(0.25),
    transducer_nonlinearity=rp.TransducerNonlinearity(0.01, 0.002),
    mains_interference=rp.MainsInterference((0.005, 0.001, 0.002), frequency_hz=50.0),
    zero_drift=rp.ZeroDrift(1e-4),
    displacement_resonance=rp.DisplacementResonance(5000.0, 0.05),
    clock_skew=rp.ClockSkew(2e-5),
)
METHODS = ("advance", "advance_stages")  # the one-pass kernel, the staged synthesis (before)


def _run(effects: rp.Effects, method: str, seed: int, seconds: float, block_s: float,
         ramping: bool) -> tuple[float, float]:
    """Real-time factors (wall, CPU) of one run of ``seconds`` of signal after one untimed ramp."""
    ph = paper_5kN_physics(effects)
    n = round(ph.sample_rate_hz * block_s)
    s = RigSynth(ph, seed=seed, crank_radius_m=0.002)
    step = getattr(s, method)
    step(n, 15.0 if ramping else 20.0)  # ramp up (not timed: one ramp per step in a real run is rare)
    blocks = round(seconds / block_s)
    t0, c0 = time.perf_counter(), time.process_time()
    for k in range(blocks):
        step(n, 10.0 + 5.0 * (k % 2) if ramping else 20.0)
    return blocks * block_s / (time.perf_counter() - t0), blocks * block_s / (time.process_time() - c0)


def measure(effects: rp.Effects, *, seconds: float = 10.0, repeats: int = 7, block_s: float = 1.0,
            ramping: bool = False) -> dict[str, tuple[float, float]]:
    """Median real-time factors (wall, CPU) per method, the methods interleaved repeat by repeat so
    that both see the same load."""
    runs: dict[str, list[tuple[float, float]]] = {m: [] for m in METHODS}
    for r in range(repeats):
        for m in METHODS:
            runs[m].append(_run(effects, m, r, seconds, block_s, ramping))
    return {m: (statistics.median(w for w, _ in v), statistics.median(c for _, c in v)) for m, v in runs.items()}


def _figures(name: str, got: dict[str, tuple[float, float]]) -> dict[str, float]:
    (wall, cpu), (wall0, cpu0) = got["advance"], got["advance_stages"]
    return {f"{name}": round(wall, 1), f"{name}_cpu": round(cpu, 1),
            f"{name}_before": round(wall0, 1), f"{name}_before_cpu": round(cpu0, 1),
            f"{name}_speedup_cpu": round(cpu / cpu0, 2)}


def main() -> None:
    load_before = os.getloadavg()
    out: dict[str, object] = {}
    out |= _figures("realtime_factor", measure(ALL_EFFECTS))
    out |= _figures("realtime_factor_no_effects", measure(rp.Effects()))
    out |= _figures("realtime_factor_all_effects_ramping", measure(ALL_EFFECTS, repeats=3, ramping=True))
    out |= _figures("realtime_factor_emulator_blocks", measure(ALL_EFFECTS, seconds=2.0, repeats=3,
                                                                block_s=256 / 20000))
    out |= {
        "before": "RigSynth.advance_stages: the staged synthesis (numpy stages, compiled harmonic sums, "
                  "filter bank and noise draws), the same samples to the bit, measured interleaved in this run",
        "target_realtime_factor": 1000,
        "effects": ALL_EFFECTS.active(),
        "sample_rate_hz": 20000,
        "channels": 2,
        "blas_threads": os.environ["OPENBLAS_NUM_THREADS"],
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
