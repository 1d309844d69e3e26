"""The station's listed identifications side by side on clean simulated runs; prints JSON.

Each run is the shipped configuration (config/sim-5kN.yaml: 5 steps 4-100 Hz, 2 s records, the
paper's k_f and b_f, no effects) simulated with its own noise seed (``station.simulate``: Eq. 3
integrated, not the estimators), then identified exactly as the daemon's worker does
(``station.run.methods``: the configuration's ``identification.methods``, by default the expert
estimator fd first and the paper's PSO+ on Eq. 11 with the Section 5.1 swarm beside it).  Per method
and parameter: the value, its stated standard uncertainty, the error against the simulated truth in
units of that uncertainty, or why the method withholds it; the agreement z with the primary; the
compute time (wall and CPU) in the worker process.

Usage: python bench/methods.py [--runs N] [--methods fd,pso+:h2,rls] [--particles N --iterations N]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
from pathlib import Path
from typing import Any

from station.config import config_to_yaml, load_config, parse_config
from station.ident.result import IdentificationResult
from station.recording import read_result
from station.run.calibrate import process_and_identify
from station.run.methods import agreement, read_outcomes
from station.simulate import simulate_run

ROOT = Path(__file__).resolve().parents[1]


def _methods(text: str) -> list[dict[str, Any]]:
    out = []
    for part in text.split(","):
        method, _, model = part.strip().partition(":")
        out.append({"method": method, **({"model": model} if model else {})})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="clean simulated runs (noise seeds 1..N)")
    ap.add_argument("--methods", default=None, help="e.g. fd,pso+:h2,rls (default: the configuration's)")
    ap.add_argument("--particles", type=int, default=None, help="swarm size (default: Section 5.1's)")
    ap.add_argument("--iterations", type=int, default=None, help="swarm iterations (default: Section 5.1's)")
    args = ap.parse_args()

    doc = __import__("yaml").safe_load(config_to_yaml(load_config(ROOT / "config" / "sim-5kN.yaml")))
    ident = doc.setdefault("identification", {})
    if args.methods:
        ident["methods"] = _methods(args.methods)
    ident["swarm"] = {k: v for k, v in (("n_particles", args.particles), ("n_iterations", args.iterations)) if v}
    cfg = parse_config(doc, "bench")
    assert cfg.simulation is not None
    s_true = cfg.simulation.truth.sensitivity_V_per_N or cfg.transducer.sensitivity_V_per_N
    truth = {"S": s_true * cfg.conditioner.gain, "k_f": cfg.simulation.truth.k_f,  # S: V/N at the DAQ
             "b_f": cfg.simulation.truth.b_f}
    per: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(1, args.runs + 1):
            path = simulate_run(cfg, Path(tmp), seed=seed)
            process_and_identify(path)
            outcomes = read_outcomes(path)
            primary = IdentificationResult.from_dict(read_result(path, outcomes[0].result_name or "") or {})
            for o in outcomes:
                e = per.setdefault(o.label, {"primary": o.primary, "runs": []})
                run: dict[str, Any] = {"seed": seed, "status": o.status, "compute_s": o.compute_s,
                                       "cpu_s": o.cpu_s, "reason": o.reason or None}
                if o.status == "done":
                    res = IdentificationResult.from_dict(read_result(path, o.result_name or "") or {})
                    agree = {} if o.primary else agreement(primary, res)
                    run["model"] = res.model
                    run["parameters"] = {
                        n: ({"value": p.value, "std": p.std, "error_in_std": (p.value - truth[n]) / p.std
                             if p.std else None, "z_vs_primary": (agree.get(n) or {}).get("z")}
                            if p.identifiable and p.value is not None else {"withheld": p.reason})
                        for n, p in res.parameters.items() if n in truth}
                e["runs"].append(run)
    summary = {}
    for label, e in per.items():
        done = [r for r in e["runs"] if r["compute_s"] is not None]
        e["median_compute_s"] = statistics.median(r["compute_s"] for r in done) if done else None
        e["median_cpu_s"] = statistics.median(r["cpu_s"] for r in done) if done else None
        params: dict[str, Any] = {}
        for n in truth:
            got = [r["parameters"][n] for r in e["runs"] if n in r.get("parameters", {})]
            vals = [g for g in got if "value" in g]
            params[n] = {"runs_with_value": len(vals), "withheld_runs": len(got) - len(vals),
                         "median_relative_error": statistics.median((g["value"] - truth[n]) / truth[n] for g in vals)
                         if vals else None,
                         "max_abs_error_in_std": max(abs(g["error_in_std"]) for g in vals) if vals else None,
                         "a_reason_withheld": next((g["withheld"] for g in got if "withheld" in g), None)}
        summary[label] = {"primary": e["primary"], "statuses": [r["status"] for r in e["runs"]],
                          "median_compute_s": e["median_compute_s"], "median_cpu_s": e["median_cpu_s"],
                          "parameters": params}
    swarm = {"n_particles": args.particles or "Section 5.1 (200)",
             "n_iterations": args.iterations or "Section 5.1 (1000 for Eq. 11)"}
    print(json.dumps({"truth": truth, "runs": args.runs, "swarm": swarm, "summary": summary, "methods": per},
                     indent=1))


if __name__ == "__main__":
    main()
