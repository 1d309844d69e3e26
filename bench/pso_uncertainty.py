"""PSO and PSO+ on clean simulated runs: does the station ever state a parameter, and with which u?  Prints JSON.

Each run is the shipped 5 kN configuration cut to one step (default the 4 Hz step the paper's
protocol takes), simulated with its own noise seed (``station.simulate``: Eq. 3 integrated, not the
estimator), then identified as the station does (``identify_recording(rec, method, form)``) for
PSO and PSO+ on Eq. 11 (``h2``) and Eq. 10 (``h1``).  Per (method, form): how often each parameter
is reported as determined, why S is withheld (the reason's first words), how often the
coefficients map to a physical parameter set, and the error of the S the coefficients map to
against the simulated truth: relative, and in units of the noise-only u of the step (the
steady-state gain/phase noise at the true parameters), i.e. how far a noise-only statement of that
S would miss (null where the step does not determine S even at the truth).  Where a parameter is
reported, z against its stated u.

Usage: python bench/pso_uncertainty.py [--runs N] [--step F:R] [--particles P --iterations N]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from station.config import config_to_yaml, load_config, parse_config
from station.ident.identify import identify_recording
from station.ident.inputs import inputs_for, model_for
from station.ident.paper.identify import DEFAULT_POLICY, steady_state_uncertainty
from station.ident.paper.protocol import PUBLISHED_SWARM, SwarmSize, paper_data
from station.recording import read_recording
from station.simulate import simulate_run

ROOT = Path(__file__).resolve().parents[1]
CASES = (("pso", "h2"), ("pso+", "h2"), ("pso", "h1"), ("pso+", "h1"))


def _config(f_hz: float, radius_m: float) -> tuple[Any, dict[str, float]]:
    doc = yaml.safe_load(config_to_yaml(load_config(ROOT / "config" / "sim-5kN.yaml")))
    doc["plan"]["steps"] = [{"crank_frequency_hz": f_hz, "crank_radius_m": radius_m}]
    doc["plan"]["record_s"] = 1.5
    cfg = parse_config(doc, "bench")
    s = (cfg.simulation.truth.sensitivity_V_per_N or cfg.transducer.sensitivity_V_per_N) * cfg.conditioner.gain
    return cfg, {"S": s, "k_f": cfg.simulation.truth.k_f, "b_f": cfg.simulation.truth.b_f}


def _run(rec: Any, truth: dict[str, float], u_noise: float, method: str, form: str, swarm: SwarmSize) -> dict[str, Any]:
    t0 = time.perf_counter()
    res = identify_recording(rec, method, form, swarm=swarm)
    th = res.extra["theta_from_coefficients"]
    err = th[0] - truth["S"]
    return {"s": time.perf_counter() - t0,
            "determined": [n for n, p in res.parameters.items() if p.identifiable],
            "z_stated": {n: (p.value - truth.get(n, np.nan)) / p.std
                         for n, p in res.parameters.items() if p.identifiable and p.value is not None and p.std},
            "why_S": " ".join((res.parameters["S"].reason or "").split(",")[0].split()[:6]),
            "physical": bool(np.all(np.isfinite(th)) and th[1] > 0 and th[2] >= 0),
            "S_rel_err": err / truth["S"], "S_err_over_noise_u": err / u_noise if u_noise > 0 else float("nan"),
            "k_f_rel_err": th[1] / truth["k_f"] - 1}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20, help="noise seeds 1..N")
    ap.add_argument("--step", default="4:0.01", help="crank frequency (Hz) : radius (m) of the one step")
    ap.add_argument("--particles", type=int, default=None, help="swarm size (default Section 5.1's)")
    ap.add_argument("--iterations", type=int, default=None, help="swarm iterations (default Section 5.1's)")
    args = ap.parse_args()
    f_hz, radius = (float(v) for v in args.step.split(":"))
    swarm = SwarmSize(args.particles, args.iterations) if (args.particles or args.iterations) else PUBLISHED_SWARM
    cfg, truth = _config(f_hz, radius)
    rows: dict[str, list[dict[str, Any]]] = {f"{m}:{f}": [] for m, f in CASES}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(1, args.runs + 1):
            rec = read_recording(simulate_run(cfg, Path(tmp) / str(seed), seed=seed))
            model = model_for(rec, "h2", inputs_for(rec))
            th_true = np.array([truth["S"], truth["k_f"], truth["b_f"]])
            cov, _ = steady_state_uncertainty(model, th_true, paper_data(rec), DEFAULT_POLICY)
            for m, f in CASES:
                rows[f"{m}:{f}"].append(_run(rec, truth, float(np.sqrt(cov[0, 0])), m, f, swarm))
    out: dict[str, Any] = {"runs": args.runs, "step": {"f_hz": f_hz, "radius_m": radius},
                           "swarm": {"n_particles": args.particles or "Section 5.1",
                                     "n_iterations": args.iterations or "Section 5.1"}, "cases": {}}
    for key, rs in rows.items():
        z = [r["z_stated"] for r in rs if r["z_stated"]]
        serr = np.abs([r["S_err_over_noise_u"] for r in rs])
        out["cases"][key] = {
            "determined_count": dict(Counter(n for r in rs for n in r["determined"])),
            "why_S_withheld": dict(Counter(r["why_S"] for r in rs if "S" not in r["determined"])),
            "physical_coefficients": sum(r["physical"] for r in rs),
            "median_abs_S_rel_err": float(np.median(np.abs([r["S_rel_err"] for r in rs]))),
            "median_abs_S_err_over_noise_u": float(np.nanmedian(serr)) if np.isfinite(serr).any() else None,
            "max_abs_S_err_over_noise_u": float(np.nanmax(serr)) if np.isfinite(serr).any() else None,
            "median_k_f_rel_err": float(np.median([r["k_f_rel_err"] for r in rs])),
            "z_stated": z, "median_s": round(statistics.median(r["s"] for r in rs), 2)}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
