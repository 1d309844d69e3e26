"""Bench of the model-gap workflow; prints JSON.

wall_s_8_steps / cpu_s_8_steps: median wall / CPU time (s) of ``analyse_recording`` (reading included)
on an 8-step recording (2 s per step, 5-95 Hz, with mains interference and transducer nonlinearity
switched on), 3 repeats; model_evaluations_8_steps: the model fits' evaluations of the rig model
(``fit.predict``, and each parameter set of ``fit.forces``) in one such analysis;
load_average_1min: the machine's load when it finished (wall time depends on it).  One BLAS thread, as
the station's processes run the analysis (``station.cli``, ``station.blas_env``; a value the user set is
kept): with OpenBLAS's pool on a loaded 2-core machine its
spinning threads were measured as analysis, 38 s of CPU for the 8-step case against 8 s.
catalogue_accuracy: share of 50 random cases (effect drawn uniformly from the catalogue, parameters
from the plausible ranges of ``station.discrepancy.scenarios``, 6 steps of 1 s, seeds 1000..1049)
whose named effects are exactly the one switched on; the 5 kN and 12.5 kN presets in turn.
wide: the same over ranges wider than those where the data decide (coupling k_c 1-10 k_f, b_c 0-0.5 b_f;
low-pass cut-off 150-3000 Hz, order 1-4; delay 1-100 us either sign, a negative one at most 45 us; the
other effects as above),
``--wide-cases`` per effect (seeds 3000..): ``confusion`` {true effect: {first named (or "none"): count}},
``tie_reported`` (a tie in the JSON: ``ties`` non-empty or a ``proposal`` separating models),
``kf_beyond_3u`` / ``bf_beyond_3u``: runs whose k_f / b_f is more than 3 reported standard uncertainties
from the truth (the target is 0), of which ``..._with_tie`` reported a tie, and ``max_abs_z_kf`` / ``_bf``.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # before numpy is imported

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from station.discrepancy import analyse_recording  # noqa: E402
from station.discrepancy import data as data_module  # noqa: E402
from station.discrepancy import fit as fit_module  # noqa: E402
from station.discrepancy.catalogue import CATALOGUE  # noqa: E402
from station.discrepancy.scenarios import (  # noqa: E402
    WIDE_EFFECTS,
    draw_effect,
    draw_scenario,
    scenario_config,
    simulate_scenario,
)
from station.discrepancy.scenarios import draw_wide as scenario_wide  # noqa: E402


def wall_8_steps(tmp: Path, repeats: int) -> tuple[float, float, int]:
    """Median wall and CPU (this process) time in s of the whole workflow on the 8-step recording, and
    the rig-model evaluations of the fits in the first repeat."""
    eff = draw_scenario(["mains_interference", "transducer_nonlinearity"], seed=8)
    path = simulate_scenario(eff, tmp / "wall", seed=8, n_steps=8, record_s=2.0)
    predict, forces = fit_module.predict, fit_module.forces
    calls = [0]

    def counted(*args: Any, **kw: Any) -> Any:
        calls[0] += 1
        return predict(*args, **kw)

    def counted_forces(plan: Any, ps: Any) -> Any:
        calls[0] += len(ps)  # one evaluation per parameter set, as when they were evaluated one by one
        return forces(plan, ps)

    times, cpu, evaluations = [], [], 0
    for i in range(repeats):
        fit_module.predict, fit_module.forces = counted, counted_forces
        data_module._PREPARED.clear()  # each repeat from the recording, as a fresh process would run it
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            analyse_recording(path)
        finally:
            fit_module.predict, fit_module.forces = predict, forces
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        evaluations = evaluations if i else calls[0]
    return statistics.median(times), statistics.median(cpu), evaluations


TRANSDUCERS = ("5kN", "12k5N")  # the transducer presets of config/, in turn (the tests take one per effect)


def accuracy(tmp: Path, cases: int) -> tuple[float, list[dict[str, object]]]:
    rng = np.random.default_rng(20261122)
    rows = []
    for i in range(cases):
        name = str(rng.choice(CATALOGUE))
        seed = 1000 + i
        transducer = TRANSDUCERS[i % len(TRANSDUCERS)]
        eff = draw_scenario([name], seed=seed, transducer=transducer)
        rep = analyse_recording(simulate_scenario(eff, tmp / f"acc{i}", seed=seed, transducer=transducer))
        named = [e.name for e in rep.effects]
        rows.append({"seed": seed, "effect": name, "transducer": transducer, "named": named, "ok": named == [name]})
    return (sum(r["ok"] for r in rows) / len(rows) if rows else float("nan")), rows


def draw_wide(name: str, rng: np.random.Generator, k_f: float, b_f: float) -> dict[str, object]:
    """An effect drawn from the wide ranges (module docstring; ``scenarios.draw_wide`` for the
    fundamental-only effects, whose negative delays are at most 45 us, an ADC's skew)."""
    if name in WIDE_EFFECTS:
        return scenario_wide(name, rng, k_f, b_f)
    return draw_effect(name, rng, k_f, b_f)


def wide(tmp: Path, per_effect: int) -> dict[str, object]:
    cfg = scenario_config({})
    assert cfg.simulation is not None
    kf, bf = cfg.simulation.truth.k_f, cfg.simulation.truth.b_f
    confusion: dict[str, dict[str, int]] = {}
    ties = beyond_k = beyond_b = beyond_k_tie = beyond_b_tie = 0
    zk: list[float] = []
    zb: list[float] = []
    for j, name in enumerate(CATALOGUE):
        row: dict[str, int] = {}
        for i in range(per_effect):
            seed = 3000 + 100 * j + i
            eff = {name: draw_wide(name, np.random.default_rng(seed), kf, bf)}
            js = analyse_recording(simulate_scenario(eff, tmp / f"w{j}-{i}", seed=seed)).to_json()
            first = js["effects"][0]["name"] if js["effects"] else "none"
            row[first] = row.get(first, 0) + 1
            prop = js.get("proposal") or {}
            tie = bool(js.get("ties")) or prop.get("measure") == "delta_chi2"
            ties += tie
            pa = js["parameters_after"]
            z_k = abs(pa["k_f"]["value"] - kf) / pa["k_f"]["std"] if pa["k_f"].get("std") else float("inf")
            z_b = abs(pa["b_f"]["value"] - bf) / pa["b_f"]["std"] if pa["b_f"].get("std") else float("inf")
            zk.append(z_k)
            zb.append(z_b)
            beyond_k += z_k > 3
            beyond_b += z_b > 3
            beyond_k_tie += z_k > 3 and tie
            beyond_b_tie += z_b > 3 and tie
        confusion[name] = row
    return {"cases": per_effect * len(CATALOGUE), "confusion": confusion, "tie_reported": ties,
            "kf_beyond_3u": beyond_k, "kf_beyond_3u_with_tie": beyond_k_tie,
            "bf_beyond_3u": beyond_b, "bf_beyond_3u_with_tie": beyond_b_tie,
            "max_abs_z_kf": round(max(zk), 3) if zk else None, "max_abs_z_bf": round(max(zb), 3) if zb else None}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cases", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--wide-cases", type=int, default=6, help="cases per effect over the wide ranges")
    ap.add_argument("--verbose", action="store_true", help="list the failed cases on stderr")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        wall, cpu, evaluations = wall_8_steps(tmp, args.repeats)
        acc, rows = accuracy(tmp, args.cases)
        wide_out = wide(tmp, args.wide_cases) if args.wide_cases > 0 else None
    if args.verbose:
        for r in rows:
            if not r["ok"]:
                print(r, file=sys.stderr)
    print(json.dumps({"wall_s_8_steps": round(wall, 3), "cpu_s_8_steps": round(cpu, 3),
                      "model_evaluations_8_steps": evaluations,
                      "load_average_1min": round(os.getloadavg()[0], 2),
                      "catalogue_accuracy": None if acc != acc else acc,
                      "wide": wide_out}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
