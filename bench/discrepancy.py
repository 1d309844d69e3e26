"""Bench of the model-gap workflow; prints JSON.

wall_s_8_steps: median wall time (s) of ``analyse_recording`` (reading included) on an 8-step recording
(2 s per step, 5-95 Hz, with mains interference and transducer nonlinearity switched on), 3 repeats.
catalogue_accuracy: share of 50 random cases (effect drawn uniformly from the catalogue, parameters
from the plausible ranges of ``station.discrepancy.scenarios``, 6 steps of 1 s, seeds 1000..1049)
whose named effects are exactly the one switched on.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from station.discrepancy import analyse_recording
from station.discrepancy.catalogue import CATALOGUE
from station.discrepancy.scenarios import draw_scenario, simulate_scenario


def wall_8_steps(tmp: Path, repeats: int) -> float:
    eff = draw_scenario(["mains_interference", "transducer_nonlinearity"], seed=8)
    path = simulate_scenario(eff, tmp / "wall", seed=8, n_steps=8, record_s=2.0)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        analyse_recording(path)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def accuracy(tmp: Path, cases: int) -> tuple[float, list[dict[str, object]]]:
    rng = np.random.default_rng(20261122)
    rows = []
    for i in range(cases):
        name = str(rng.choice(CATALOGUE))
        seed = 1000 + i
        eff = draw_scenario([name], seed=seed)
        rep = analyse_recording(simulate_scenario(eff, tmp / f"acc{i}", seed=seed))
        named = [e.name for e in rep.effects]
        rows.append({"seed": seed, "effect": name, "named": named, "ok": named == [name]})
    return (sum(r["ok"] for r in rows) / len(rows) if rows else float("nan")), rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cases", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--verbose", action="store_true", help="list the failed cases on stderr")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        wall = wall_8_steps(tmp, args.repeats)
        acc, rows = accuracy(tmp, args.cases)
    if args.verbose:
        for r in rows:
            if not r["ok"]:
                print(r, file=sys.stderr)
    print(json.dumps({"wall_s_8_steps": round(wall, 3), "catalogue_accuracy": None if acc != acc else acc}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
