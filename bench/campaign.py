"""Benchmark of the multi-mass campaign (station.ident.campaign.identify); prints JSON.

1. Monte Carlo: N noise draws (seeds) of a campaign of three recordings of the simulated 5 kN
   transducer (config/sim-5kN.yaml, end mass 0.12 kg) with top masses 5, 15 and 25.717 kg (steps
   4, 20, 50, 100 Hz), each recording written by station.simulate (the physics of Eq. 3, not the
   code under test).  Per parameter: mean estimate, empirical standard deviation, mean reported
   noise-only standard uncertainty (budget 'noise': the simulator's masses and chain are exact) and
   mean combined one, their ratios to the empirical scatter, and the z = (estimate - truth) / combined
   of every draw (max |z|, fraction within 2).
2. Mass spread: two recordings, top masses 25.717 kg and 25.717 kg + spread; the status and the
   relative standard uncertainty of S per spread (where "too alike" starts).
3. Time: median wall time of identify_campaign on three recordings.

Usage: python bench/campaign.py [--draws N] [--record-s S]
"""

from __future__ import annotations

import argparse
import copy
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from station.config import default_config_path, parse_config
from station.ident.campaign.identify import identify_campaign
from station.recording import read_recording
from station.simulate import simulate_run

END_MASS = 0.12
TRUTH = {"S": 2.0e-3, "m_e": END_MASS, "k_f": 2.91e7, "b_f": 17136.0}
STEPS = ((4.0, 0.01), (20.0, 0.002), (50.0, 6e-4), (100.0, 1.5e-4))


def _cfg(top: float, record_s: float) -> object:
    d = copy.deepcopy(yaml.safe_load(default_config_path().read_text(encoding="utf-8")))
    d["plan"].update(settle_s=0.2, record_s=record_s,
                     steps=[{"crank_frequency_hz": f, "crank_radius_m": r} for f, r in STEPS])
    d["rig"].update(acceleration_hz_per_s=100.0, top_mass_kg=top)  # the crank drive's fastest ramp
    d["transducer"]["end_mass_kg"] = END_MASS
    d["simulation"].update(pre_roll_s=0.1, effects={})
    return parse_config(d)


def _campaign(tmp: Path, tops: tuple[float, ...], seed: int, record_s: float) -> list:
    return [read_recording(simulate_run(_cfg(t, record_s), tmp, seed=seed * 10 + i)) for i, t in enumerate(tops)]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=30)
    ap.add_argument("--record-s", type=float, default=0.5)
    args = ap.parse_args()
    est: dict[str, list[float]] = {n: [] for n in TRUTH}
    noise: dict[str, list[float]] = {n: [] for n in TRUTH}
    comb: dict[str, list[float]] = {n: [] for n in TRUTH}
    times = []
    statuses = []
    with tempfile.TemporaryDirectory() as td:
        for k in range(args.draws):
            recs = _campaign(Path(td) / f"d{k}", (5.0, 15.0, 25.717), k + 1, args.record_s)
            t0 = time.perf_counter()
            res = identify_campaign(recs)
            times.append(time.perf_counter() - t0)
            statuses.append(res.status)
            for n in TRUTH:
                p = res.parameter(n)
                est[n].append(float(p.value))  # type: ignore[arg-type]
                comb[n].append(float(p.std))  # type: ignore[arg-type]
                noise[n].append(res.budget[n]["contributions"]["noise"])
        spread = {}
        for s in (0.05, 0.2, 0.5, 1.0, 2.0, 5.0, 20.0):
            res = identify_campaign(_campaign(Path(td) / f"s{s}", (25.717, 25.717 + s), 99, args.record_s))
            sep = next(c for c in res.checks if c.name == "end_mass_separation")
            spread[f"{s:g}"] = {"status": res.status, "S_rel_std": sep.values.get("S_rel_std"),
                                "m_e_std_kg": sep.values.get("m_e_std_kg"), "severity": sep.severity}
    out: dict[str, object] = {"draws": args.draws, "record_s": args.record_s, "statuses": sorted(set(statuses)),
                              "top_masses_kg": [5.0, 15.0, 25.717], "truth": TRUTH}
    for n, truth in TRUTH.items():
        v = np.array(est[n])
        emp = float(np.std(v, ddof=1))
        z = (v - truth) / np.array(comb[n])
        out[n] = {"mean": float(np.mean(v)), "bias_over_empirical_std": float((np.mean(v) - truth) / emp),
                  "empirical_std": emp, "reported_noise_std": float(np.mean(noise[n])),
                  "reported_combined_std": float(np.mean(comb[n])),
                  "noise_over_empirical": float(np.mean(noise[n]) / emp),
                  "combined_over_empirical": float(np.mean(comb[n]) / emp),
                  "max_abs_z": float(np.max(np.abs(z))), "fraction_abs_z_below_2": float(np.mean(np.abs(z) < 2))}
    out["mass_spread"] = spread
    out["identify_campaign_median_s"] = statistics.median(times)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
