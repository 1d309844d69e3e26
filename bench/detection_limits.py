"""Detection limits of the model-gap workflow, measured; prints JSON.

For each catalogue effect, the smallest size that ``station discrepancy`` names right (the first and
only effect named is the one simulated) in at least 9 of 10 seeded simulations, on a stated plan and
noise: the 5 kN preset (config/sim-5kN.yaml: displacement noise 0.2 um, conditioner noise 0.5 mV)
with 6 steps of 1 s log-spaced over 5-95 Hz at one radius (``scenarios.plan_steps``).  Sizes move on a
ladder by a factor of 2 from a start value (down while 9/10 hold, up until they do), at most
``--levels`` rungs, so a limit is known to a factor of 2: the table gives the smallest size that passed
and the largest that failed (the rate at each rung is in ``ladder``).  Effects that act only on the
fundamental (delay, low-pass, coupling) can also be named as one another (a tie); those trials are
counted as ``misnamed`` with the name given and the next run the report proposed
(``proposal.steps``): the plan needed to separate that pair.

Run: ``python bench/detection_limits.py [--seeds 10] [--levels 4] [--only NAME ...] [--start NAME=SIZE ...]``.
The figures in docs/discrepancy.md: ``--levels 2`` in two groups, then ``--levels 2 --only channel_delay
crank_harmonics transducer_nonlinearity --start channel_delay=1.5e-6 crank_harmonics=4
transducer_nonlinearity=5e-5`` (each about 3-5 min on a loaded 2-core machine).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

from station.discrepancy import analyse_recording
from station.discrepancy.scenarios import scenario_config, simulate_scenario

cfg0 = scenario_config({})
assert cfg0.simulation is not None
K_F, B_F = cfg0.simulation.truth.k_f, cfg0.simulation.truth.b_f

# effect -> (size name, unit, start, ladder factor towards a SMALLER effect, configuration of a size)
LADDERS: dict[str, tuple[str, str, float, float, Any]] = {
    "channel_delay": ("delay_s", "s", 6e-6, 0.5, lambda s: {"delay_s": s}),
    "conditioner_lowpass": ("cutoff_hz (order 2)", "Hz", 500.0, 2.0, lambda s: {"order": 2, "cutoff_hz": s}),
    "coupling_compliance": ("k_c / k_f (b_c = 0)", "1", 3.0, 2.0, lambda s: {"k_c": s * K_F, "b_c": 0.0}),
    "crank_harmonics": ("rod_length_m", "m", 1.0, 2.0, lambda s: {"rod_length_m": s}),
    "transducer_nonlinearity": ("quadratic (cubic 0)", "1", 2e-4, 0.5,
                                lambda s: {"quadratic": s, "cubic": 0.0}),
    "mains_interference": ("amplitude_V (50 Hz, 1 harmonic)", "V", 3e-5, 0.5,
                           lambda s: {"frequency_hz": 50.0, "amplitudes_V": [s], "phases_rad": [0.7]}),
    "zero_drift": ("rate_V_per_s", "V/s", 3e-6, 0.5, lambda s: {"rate_V_per_s": s, "quadratic_V_per_s2": 0.0}),
}


def trial_rate(name: str, size: float, seeds: int, tmp: Path, walls: list[float]) -> dict[str, Any]:
    """Named-right count over ``seeds`` simulations of effect ``name`` at ``size``."""
    make = LADDERS[name][4]
    named: Counter[str] = Counter()
    proposals = []
    for i in range(seeds):
        seed = 5000 + i
        path = simulate_scenario({name: make(size)}, tmp / f"{name}-{size:.4g}-{i}", seed=seed)
        t0 = time.perf_counter()
        rep = analyse_recording(path, max_effects=1)
        walls.append(time.perf_counter() - t0)
        got = rep.effects[0].name if rep.effects else "none"
        named[got] += 1
        if got not in (name, "none") and rep.proposal is not None:
            proposals.append([s[0] for s in rep.proposal.steps])
        path.unlink(missing_ok=True)
    return {"size": size, "named_right": named[name], "of": seeds,
            "named": dict(named), "proposed_added_hz": proposals[:3]}


def ladder(name: str, seeds: int, levels: int, tmp: Path, walls: list[float]) -> dict[str, Any]:
    label, unit, size, smaller, _ = LADDERS[name]
    need = -(-9 * seeds // 10)
    rungs = [trial_rate(name, size, seeds, tmp, walls)]
    direction = smaller if rungs[0]["named_right"] >= need else 1 / smaller
    for _ in range(levels - 1):
        size *= direction
        rungs.append(trial_rate(name, size, seeds, tmp, walls))
        passed = rungs[-1]["named_right"] >= need
        if (direction == smaller) != passed:  # crossed the limit
            break
    ok = [r["size"] for r in rungs if r["named_right"] >= need]
    bad = [r["size"] for r in rungs if r["named_right"] < need]
    key = (lambda s: s) if smaller < 1 else (lambda s: -s)  # "smallest effect"
    return {"effect": name, "size": label, "unit": unit,
            "limit_9_of_10": min(ok, key=key) if ok else None,
            "largest_failing": max(bad, key=key) if bad else None, "ladder": rungs}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--levels", type=int, default=4)
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--start", nargs="*", default=[], metavar="EFFECT=SIZE",
                    help="start size of an effect's ladder (e.g. channel_delay=1.5e-6)")
    args = ap.parse_args()
    for item in args.start:
        name, _, value = item.partition("=")
        a = LADDERS[name]
        LADDERS[name] = (a[0], a[1], float(value), a[3], a[4])
    names = args.only or list(LADDERS)
    walls: list[float] = []
    out = []
    with tempfile.TemporaryDirectory() as d:
        for n in names:
            out.append(ladder(n, args.seeds, args.levels, Path(d), walls))
            print(json.dumps(out[-1]), file=sys.stderr, flush=True)
    plan = {"transducer": "5kN", "steps": 6, "f_hz": [5, 95], "record_s": 1.0,
            "displacement_noise_m": 2e-7, "conditioner_noise_V": 5e-4, "max_effects": 1}
    print(json.dumps({"plan": plan, "limits": out,
                      "median_wall_s": round(statistics.median(walls), 3) if walls else None}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
