"""``station paper``: the paper's Table 1, noise study (Sec. 4.2) and experiment protocol (Sec. 5)
regenerated next to the published figures, plus our expert estimators on the same data.

Assumptions the paper leaves open (stated in the report): Cases I/II sample the input
5 sin(2 pi 4 t) at 10 Hz for 100 points (with these, PSO reaches the published 1e-31 in ~850
iterations); Section 5 resamples to 500 Hz; the Section 5 velocity limit and iteration counts are
not given (see ``ident.paper.pso.SECTION5_H2``).  SNR = mean square of the clean output / noise variance.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.signal import freqz, lfilter

from station.ident.fd.identify import identify_fd
from station.ident.identify import identify_recording
from station.ident.paper.protocol import PaperProtocol, paper_data
from station.ident.paper.pso import CASE_I, CASE_II, PsoResult, output_error_objective, run_pso
from station.ident.result import json_floats
from station.recording import read_recording

log = logging.getLogger(__name__)
CASES = {"I": (np.array([0.25, 0.5, 0.25]), np.array([1.0, -0.3, 0.4]), "h2", CASE_I),
         "II": (np.array([0.0, 1.0, -0.9, 0.81, -0.729]),
                np.array([1.0, -0.04, -0.2775, 0.2101, -0.14]), "h1", CASE_II)}
PAPER_TABLE1 = {"I": {"pso_mse": 1.0402e-31, "pso+_mse": 9.0450e-18, "pso_iterations": 880,
                      "pso+_iterations": "<100"},
                "II": {"pso_mse": 2.5862e-31, "pso+_mse": 5.4054e-17, "pso_iterations": 1416,
                       "pso+_iterations": 850}}
PAPER_NOISE = {10: 80.1880, 20: 7.9021, 30: 0.9229, 40: 0.0921, 50: 0.0092}
PAPER_SEC5 = {"5kN": {"rls_III": 19.7667, "pso+_III": 0.0191, "pso+_IV": 0.0186, "k_f": 0.291e8,
                      "b_f": 17136.0},
              "12.5kN": {"rls_V": 0.9304, "pso+_V": 0.0020, "pso+_VI": 0.0017, "k_f": 0.246e8,
                         "b_f": 3032.0}}
FS_CASES, M_CASES = 10.0, 100


def case_data(case: str) -> tuple[np.ndarray, np.ndarray]:
    """Input 5 sin(2 pi 4 t) at FS_CASES Hz (M_CASES points) and the benchmark's output."""
    b, a, _, _ = CASES[case]
    x = 5 * np.sin(2 * np.pi * 4 * np.arange(M_CASES) / FS_CASES)
    return x, lfilter(b, a, x)


def compare_pso(case: str, seed: int, n_iter: int | None = None) -> dict[str, Any]:
    """PSO and PSO+ on one case with the same seed; where and why their histories part."""
    _, _, form, settings = CASES[case]
    if n_iter:
        settings = replace(settings, n_iterations=n_iter)
    x, y = case_data(case)
    n_dim = 4 if form == "h2" else 10
    runs: dict[str, PsoResult] = {v: run_pso(output_error_objective(form, x, y), n_dim,
                                             replace(settings, variant=v), seed) for v in ("pso", "pso+")}
    a, b = runs["pso"].mse_history, runs["pso+"].mse_history
    diff = np.nonzero(a != b)[0]
    ties = np.nonzero(runs["pso+"].tie_decisions)[0]
    out: dict[str, Any] = {"seed": seed, "first_difference": int(diff[0]) if diff.size else None,
                           "first_tie": int(ties[0]) if ties.size else None,
                           "mse_at_first_difference": float(a[diff[0] - 1]) if diff.size else None}
    for v, r in runs.items():
        below = np.nonzero(r.mse_history < 1e-10)[0]
        looks_flat = np.nonzero(np.exp(-r.mse_history) > 0.999)[0]
        out[v] = {"mse": r.mse, "iterations_to_converge": r.iterations_to_converge,
                  "iterations_to_mse_1e-10": int(below[0]) if below.size else None,
                  "iterations_to_exp_fitness_0.999": int(looks_flat[0]) if looks_flat.size else None,
                  "coefficients_normalised": (r.position / r.position[1 if form == "h2" else 5]).tolist(),
                  "tie_decisions": int(r.tie_decisions.sum())}
    out["_runs"] = runs
    return out


def table1(seeds: list[int], n_iter: int | None) -> dict[str, Any]:
    """Table 1 for Cases I and II over the given seeds."""
    res: dict[str, Any] = {}
    for case in CASES:
        rows = [compare_pso(case, s, n_iter) for s in seeds]
        res[case] = {"paper": PAPER_TABLE1[case], "runs": rows,
                     "median": {v: {"mse": float(np.median([r[v]["mse"] for r in rows])),
                                    "iterations_to_converge": float(np.median(
                                        [r[v]["iterations_to_converge"] for r in rows]))}
                                for v in ("pso", "pso+")}}
    return res


def noise_study(seed: int, n_iter: int | None) -> dict[str, Any]:
    """Section 4.2: Case I with white output noise at 10-50 dB SNR, PSO+ with Case I settings."""
    x, y = case_data("I")
    settings = replace(CASE_I, n_iterations=n_iter or CASE_I.n_iterations, variant="pso+")
    rows = []
    for snr in (10, 20, 30, 40, 50):
        var = float(np.mean(y**2)) / 10 ** (snr / 10)
        rng = np.random.default_rng(seed + snr)
        yn = y + rng.normal(0.0, np.sqrt(var), y.size)
        r = run_pso(output_error_objective("h2", x, yn), 4, settings, seed)
        rows.append({"snr_db": snr, "mse": r.mse, "noise_variance": var, "mse_over_noise_variance": r.mse / var,
                     "paper_mse": PAPER_NOISE[snr], "_y": yn, "_pos": r.position})
    return {"rows": rows, "x": x}


def section5(out: Path, seeds: list[int], quick: bool) -> dict[str, Any]:
    """Section 5 protocol on simulated 5 kN and 12.5 kN transducers, plus our estimators."""
    from sinecal_config import config_file

    from station.config import load_config
    from station.simulate import simulate_run

    res: dict[str, Any] = {}
    for name, cfgfile, cases in (("5kN", "sim-5kN.yaml", ("III", "IV")),
                                 ("12.5kN", "sim-12k5N.yaml", ("V", "VI"))):
        cfg = load_config(config_file(cfgfile))
        path = simulate_run(cfg, out / "sim", seed=seeds[0])
        rec = read_recording(path)
        truth = cfg.simulation.truth if cfg.simulation else None
        row: dict[str, Any] = {"recording": str(path), "paper": PAPER_SEC5[name],
                               "truth": {"k_f": truth.k_f, "b_f": truth.b_f} if truth else None}
        rls = identify_recording(rec, "rls", "h2")
        d = paper_data(rec, PaperProtocol())
        half = d.x_test.size // 2
        with np.errstate(all="ignore"):
            e_rls = lfilter(json_floats(rls.extra, "b"), json_floats(rls.extra, "a"), d.x_test) - d.y_test
        row[f"rls_{cases[0]}"] = {"testing_mse_V2": rls.extra["testing_mse_V2"],
                                  "testing_mse_second_half_V2": float(np.mean(e_rls[half:] ** 2)),
                                  "poles_abs": np.abs(np.roots(json_floats(rls.extra, "a"))).tolist()}
        for case, form in zip(cases, ("h2", "h1"), strict=True):
            runs = [identify_recording(rec, "pso+", form, seed=s) for s in seeds]
            row[f"pso+_{case}"] = {
                "testing_mse_V2": [r.extra["testing_mse_V2"] for r in runs],
                "iterations_to_converge": [r.extra["iterations_to_converge"] for r in runs],
                "theta_from_coefficients": [r.extra["theta_from_coefficients"] for r in runs],
                "identifiable": {n: p.identifiable for n, p in runs[0].parameters.items()},
                "reasons": {n: p.reason for n, p in runs[0].parameters.items() if not p.identifiable}}
            if form == "h2":
                row["_pso_h2"] = runs[0]
                e = lfilter(json_floats(runs[0].extra, "b"), json_floats(runs[0].extra, "a"), d.x_test) - d.y_test
                row[f"pso+_{case}"]["testing_mse_second_half_V2"] = float(np.mean(e[half:] ** 2))
        row["_rls"] = rls
        single = replace(rec, steps=[rec.steps[0]])
        fd1 = identify_fd(single, "sdof")
        row["expert_single_4Hz"] = {n: p.to_dict() for n, p in fd1.parameters.items()}
        fd = identify_fd(rec, "sdof")
        row["expert_stepped_sine"] = {n: p.to_dict() for n, p in fd.parameters.items()}
        if truth:
            k_f, b_f = fd.parameter("k_f").value, fd.parameter("b_f").value
            row["expert_rel_err"] = {"k_f": k_f / truth.k_f - 1 if k_f is not None else None,
                                     "b_f": b_f / truth.b_f - 1 if b_f is not None else None}
        row["_fd"], row["_data"] = fd, d
        res[name] = row
    return res


def noise_power_text(noise: dict[str, Any]) -> str:
    """Why the paper's absolute noise-study MSEs stay unexplained, with the numbers: an MSE at the
    noise variance implies an output power MSE 10^(SNR/10); the Case I filter cannot produce it."""
    b, a, _, _ = CASES["I"]
    _, h = freqz(b, a, worN=1 << 16)
    g = float(np.max(np.abs(h)))
    implied = [PAPER_NOISE[s] * 10 ** (s / 10) for s in sorted(PAPER_NOISE)]
    ours = float(np.mean(case_data("I")[1] ** 2))
    noise["output_power"] = {"max_gain": g, "bound": (5 * g) ** 2 / 2, "ours": ours, "paper_implied": implied}
    return (f"The paper's absolute MSEs are unexplained: with the MSE at the noise variance they imply an output "
            f"power of {min(implied):.0f}-{max(implied):.0f} (MSE x 10^(SNR/10)), but the Case I filter's "
            f"largest gain is {g:.4g}, so with the input 5 sin(2 pi 4 t) its steady-state output power stays "
            f"below (5 x {g:.4g})^2 / 2 = {(5 * g) ** 2 / 2:.3g} at any sampling rate (ours: {ours:.3g}). No "
            "sampling assumption reconciles them; they do fall by 10x per 10 dB, as ours do.")


def explanations(t1: dict[str, Any], noise: dict[str, Any], sec5: dict[str, Any]) -> list[str]:
    """Why our figures differ from the paper's, with the measured numbers."""
    r = t1["I"]["runs"][0]
    ii = t1["II"]["runs"]
    n_it2 = len(ii[0]["_runs"]["pso"].mse_history) - 1
    best2 = min(min(x["pso"]["mse"], x["pso+"]["mse"]) for x in ii)
    out = [
        f"Case I seed {r['seed']}: PSO and PSO+ follow identical Gbest histories up to iteration "
        f"{r['first_difference']}; PSO+ made its first decision that differs from the MSE's own at iteration "
        f"{r['first_tie']}: exp(-MSE) underflows to 0.0 for MSE > 745, so wildly unstable particles tie. "
        "Without such ties (a bounded objective, tests/test_ident_pso.py) the histories are identical "
        "down to MSE 1e-15.",
        f"PSO+ stops improving at MSE {r['pso+']['mse']:.3g} (iteration {r['pso+']['iterations_to_converge']}) "
        f"while PSO goes on to {r['pso']['mse']:.3g} (iteration {r['pso']['iterations_to_converge']}): "
        "exp(-MSE) rounds to 1.0 for MSE < 1.1e-16, so below that PSO+ sees no improvement. This, not "
        "faster convergence, is the paper's 1e-17 vs 1e-31. Plotted as exp(-MSE), PSO+ looks converged "
        f"(> 0.999) from iteration {r['pso+']['iterations_to_exp_fitness_0.999']}; PSO's MSE plotted the "
        f"same way would look flat from iteration {r['pso']['iterations_to_exp_fitness_0.999']}.",
        f"Case II: over {len(ii)} seeds neither variant gets below MSE {best2:.3g} in {n_it2} iterations"
        " with our sampling assumption (10 Hz, 100 points); the paper's Case II result "
        "(-2 z^-1 + ..., a0 = -2) sits exactly on the position limit, where clipping fixes (our reading) "
        "the scale the 10 coefficients otherwise leave free; we do not reproduce its 2.6e-31.",
        "Noise study: the PSO+ MSE is close to the added noise variance (ratios "
        + ", ".join(f"{row['mse_over_noise_variance']:.2f}" for row in noise["rows"])
        + " for 10..50 dB): the fitted model is close to the truth and the residual is the noise. "
        + noise_power_text(noise),
        "Section 5: one 4 Hz sine carries two real numbers (gain and phase of H). k_f and b_f from Cases "
        "III/V are therefore not determined by the data; the values the coefficients map to change from "
        "seed to seed (see theta_from_coefficients), and the expert estimator reports them as not "
        "identifiable on the same record, while the stepped-sine run gives them to < 1e-4.",
    ]
    r5 = sec5["5kN"]
    out.append(
        "RLS (Eq. 17) is an equation-error estimator (noisy past outputs in its regressor bias the poles). "
        f"On the 5 kN record its testing MSE is {r5['rls_III']['testing_mse_V2']:.3g} V^2 over the 400 "
        f"points but {r5['rls_III']['testing_mse_second_half_V2']:.3g} over their second half (PSO+: "
        f"{np.median(r5['pso+_III']['testing_mse_V2']):.3g} and {r5['pso+_III']['testing_mse_second_half_V2']:.3g}); "
        f"its poles have |p| = {', '.join(f'{p:.4f}' for p in r5['rls_III']['poles_abs'])}. Its error is the "
        "start-up transient of the model run from rest; in steady state RLS fits better than PSO+. "
        "The paper's 1000x (Table 2) is not reproduced; ours is "
        f"{r5['rls_III']['testing_mse_V2'] / np.median(r5['pso+_III']['testing_mse_V2']):.3g}x.")
    return out


def run_paper(out: str | Path = "recordings/paper", *, quick: bool = False, seed: int = 0) -> dict[str, Any]:
    """Everything; PNGs into ``out``.  quick: 1 seed and fewer iterations (a few seconds)."""
    from station.ident.paper.plots import save_plots

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    seeds = [seed] if quick else [seed + i for i in range(5)]
    n_iter = 300 if quick else None
    t1 = table1(seeds, n_iter)
    noise = noise_study(seed, n_iter)
    sec5 = section5(out, seeds[:1] if quick else seeds[:3], quick)
    figures = save_plots(out, t1, noise, sec5)
    report = {"assumptions": {"cases_sample_rate_hz": FS_CASES, "cases_points": M_CASES,
                              "section5_resample_hz": PaperProtocol().resample_hz, "seeds": seeds,
                              "iterations_override": n_iter},
              "table1": t1, "noise_study": noise["rows"], "section5": sec5,
              "explanations": explanations(t1, noise, sec5), "figures": [str(f) for f in figures]}
    report["noise_output_power"] = noise.get("output_power")
    return _public(report)


def _public(obj: Any) -> Any:
    """Drop private (underscore) entries and make numpy values JSON-safe."""
    if isinstance(obj, dict):
        return {k: _public(v) for k, v in obj.items() if not str(k).startswith("_")}
    if isinstance(obj, list | tuple):
        return [_public(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def format_report(rep: dict[str, Any]) -> str:
    """Text form of the report."""
    lines = ["Table 1 (median over seeds; paper in brackets)"]
    for case, t in rep["table1"].items():
        p, m = t["paper"], t["median"]
        lines.append(f"  Case {case}: PSO MSE {m['pso']['mse']:.3g} [{p['pso_mse']:.4g}], converged at "
                     f"{m['pso']['iterations_to_converge']:.0f} [{p['pso_iterations']}]; PSO+ MSE "
                     f"{m['pso+']['mse']:.3g} [{p['pso+_mse']:.4g}], converged at "
                     f"{m['pso+']['iterations_to_converge']:.0f} [{p['pso+_iterations']}]")
    lines.append("Noise study (PSO+ MSE [paper], noise variance)")
    for r in rep["noise_study"]:
        lines.append(f"  {r['snr_db']} dB: {r['mse']:.4g} [{r['paper_mse']}], {r['noise_variance']:.4g}")
    lines.append("Section 5 (testing MSE in V^2; the paper's unit is not stated)")
    for name, r in rep["section5"].items():
        keys = [k for k in r if k.startswith(("rls_", "pso+_"))]
        lines.append(f"  {name}: " + "; ".join(
            f"{k} {np.median(np.atleast_1d(r[k]['testing_mse_V2'])):.3g} [{r['paper'].get(k)}]" for k in keys))
        e = r["expert_stepped_sine"]
        lines.append(f"    expert (stepped sine): k_f {e['k_f']['value']:.6g} +- {e['k_f']['std']:.2g} N/m, "
                     f"b_f {e['b_f']['value']:.6g} +- {e['b_f']['std']:.2g} N*s/m; on the 4 Hz step alone "
                     f"k_f identifiable={r['expert_single_4Hz']['k_f']['identifiable']}, "
                     f"b_f identifiable={r['expert_single_4Hz']['b_f']['identifiable']}")
    lines.append("Why the figures differ:")
    lines += [f"  - {e}" for e in rep["explanations"]]
    lines.append("Figures: " + ", ".join(rep["figures"]))
    return "\n".join(lines)
