"""RLS (Eq. 17) on clean simulated runs: is S right within its stated uncertainty?  Prints JSON.

Each run is the shipped 5 kN configuration cut to its 4 Hz step (the one the paper's protocol
takes), simulated with its own noise seed (``station.simulate``: Eq. 3 integrated, not the
estimator), then identified as the station does (``identify_recording(rec, "rls", "h2")``).  Per
run: the error of S against the simulated truth in units of (a) the noise-only u the station used
to state (the budget's ``noise`` term) and (b) the combined u it states now (plus
``unidentified_dynamics``).  Beside them the decomposition of where the miss comes from, each
candidate measured on the same runs:

* ``unidentified_dynamics``: the regression of the S error on RLS's k_f error (slope against
  M w^2 / k_f, the sensitivity of S to k_f at fixed H(4 Hz)) and the z spread left once it is removed;
* ``equation_error_bias``: mean errors of RLS's S and k_f (with their standard errors), and of the
  same regression without RLS's start P0 = 1e6 I (ordinary least squares on Eq. 17);
* ``start_up``: RLS's final theta against the batch ridge solution (Phi^T Phi + I/delta)^-1 Phi^T y;
* ``discretisation``: |H2(e^{jwT}) / H9(jw) - 1| at 4 Hz and 500 Hz with the true parameters;
* ``displacement_channel``: the same z spread with the displacement noise switched off;
* ``covariance_forms``: the RLS covariance mapped to S: sigma^2 P (white), sandwich with 0, 2, 5
  Newey-West lags (the spread of z for each).

Usage: python bench/rls_uncertainty.py [--runs N]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from station.config import config_to_yaml, load_config, parse_config
from station.ident.identify import identify_recording
from station.ident.inputs import inputs_for, model_for
from station.ident.models import DigitalTF
from station.ident.paper.protocol import paper_data
from station.ident.paper.rls import regressors, rls_covariance, rls_h2
from station.ident.paper.rls_uncertainty import coefficient_jacobian
from station.recording import read_recording
from station.simulate import simulate_run

ROOT = Path(__file__).resolve().parents[1]


def _config(displacement_noise: bool) -> tuple[Any, dict[str, float]]:
    doc = yaml.safe_load(config_to_yaml(load_config(ROOT / "config" / "sim-5kN.yaml")))
    doc["plan"]["steps"] = [{"crank_frequency_hz": 4.0, "crank_radius_m": 0.01}]
    doc["plan"]["record_s"] = 1.5
    if not displacement_noise:
        doc["simulation"]["displacement_noise_m"] = 0.0
    cfg = parse_config(doc, "bench")
    s = (cfg.simulation.truth.sensitivity_V_per_N or cfg.transducer.sensitivity_V_per_N) * cfg.conditioner.gain
    return cfg, {"S": s, "k_f": cfg.simulation.truth.k_f, "b_f": cfg.simulation.truth.b_f}


def _spread(z: list[float]) -> dict[str, float]:
    a = np.abs(np.asarray(z))
    return {"sd": round(float(np.std(z)), 3), "max_abs": round(float(a.max()), 3),
            "share_abs_le_2": round(float(np.mean(a <= 2)), 3), "n_abs_gt_4": int(np.sum(a > 4))}


def _run(cfg: Any, truth: dict[str, float], seed: int, folder: Path) -> dict[str, float]:
    rec = read_recording(simulate_run(cfg, folder, seed=seed))
    res = identify_recording(rec, "rls", "h2")
    s = res.parameters["S"]
    assert s.value is not None and s.std is not None
    terms = res.budget["S"]["contributions"]
    th_phys = res.extra["theta_from_coefficients"]
    data = paper_data(rec)
    model = model_for(rec, "h2", inputs_for(rec))
    r = rls_h2(data.x_id, data.y_id)
    phi = regressors(data.x_id, data.y_id)
    ridge = np.linalg.solve(phi.T @ phi + np.eye(3) / 1e6, phi.T @ data.y_id[2:])
    ols = np.linalg.lstsq(phi, data.y_id[2:], rcond=None)[0]
    G = coefficient_jacobian(model, r.theta, data.T)
    e = data.y_id[2:] - phi @ r.theta
    u_forms = {"white_sigma2_P": float(np.sqrt(G[0] @ (np.mean(e**2) * r.P) @ G[0]))}
    for lags in (0, 2, 5):
        cov = rls_covariance(data.x_id, data.y_id, r, lags=lags)
        u_forms[f"sandwich_lags_{lags}"] = float(np.sqrt(G[0] @ cov @ G[0]))
    ols_phys = model.from_digital(DigitalTF(np.array([ols[2], 2 * ols[2], ols[2]]), np.array([1.0, ols[0], ols[1]]),
                                            data.T))
    th = np.array([truth["S"], truth["k_f"], truth["b_f"]])
    tf = model.to_digital(th, data.T)
    zq = np.exp(2j * np.pi * data.f_hz * data.T)
    h2 = np.polyval(tf.b, zq) / np.polyval(tf.a, zq)
    err = s.value - truth["S"]
    return {"S_rel_err": err / truth["S"], "z_noise_only": err / terms["noise"], "z_stated": err / s.std,
            "u_noise_rel": terms["noise"] / truth["S"], "u_dynamics_rel": terms["unidentified_dynamics"] / truth["S"],
            "u_stated_rel": s.std / truth["S"], "k_f_rel_err": th_phys[1] / truth["k_f"] - 1,
            "ols_S_rel_err": ols_phys[0] / truth["S"] - 1, "ols_k_f_rel_err": ols_phys[1] / truth["k_f"] - 1,
            "rls_vs_ridge_max_rel": float(np.max(np.abs(r.theta - ridge) / np.abs(ridge))),
            "M_w2_over_k_f": model.M * (2 * np.pi * data.f_hz) ** 2 / truth["k_f"],
            "H2_over_H9_minus_1": float(abs(h2 / model.response(th, np.array([data.f_hz]))[0] - 1)),
            **{f"z_{k}": err / v for k, v in u_forms.items()}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=40, help="noise seeds 1..N")
    args = ap.parse_args()
    out: dict[str, Any] = {"runs": args.runs}
    with tempfile.TemporaryDirectory() as tmp:
        for noisy in (True, False):
            cfg, truth = _config(noisy)
            rows = [_run(cfg, truth, seed, Path(tmp) / f"{noisy}-{seed}") for seed in range(1, args.runs + 1)]
            col = {k: [r[k] for r in rows] for k in rows[0]}
            if not noisy:
                out["displacement_channel"] = {"z_noise_only_without_displacement_noise": _spread(col["z_noise_only"]),
                                               "z_stated_without_displacement_noise": _spread(col["z_stated"])}
                continue
            sens = col["M_w2_over_k_f"][0]
            kf, srel = np.asarray(col["k_f_rel_err"]), np.asarray(col["S_rel_err"])
            slope, icpt = np.polyfit(kf, srel, 1)
            left = (srel - (slope * kf + icpt)) / np.asarray(col["u_noise_rel"])
            n = len(rows)
            out.update({
                "truth": truth,
                "old_noise_only": {"z": _spread(col["z_noise_only"]),
                                   "median_u_rel": statistics.median(col["u_noise_rel"])},
                "new_stated": {"z": _spread(col["z_stated"]), "median_u_rel": statistics.median(col["u_stated_rel"]),
                               "median_u_unidentified_dynamics_rel": statistics.median(col["u_dynamics_rel"])},
                "unidentified_dynamics": {
                    "k_f_rel_err_sd": float(np.std(kf)), "slope_S_on_k_f": float(slope),
                    "expected_M_w2_over_k_f": float(sens), "corr": float(np.corrcoef(kf, srel)[0, 1]),
                    "z_noise_only_after_removing_it": _spread(list(left))},
                "equation_error_bias": {
                    "rls_S_mean_rel_err": float(np.mean(srel)),
                    "its_standard_error": float(np.std(srel) / np.sqrt(n)),
                    "rls_k_f_mean_rel_err": float(np.mean(kf)),
                    "its_standard_error_k_f": float(np.std(kf) / np.sqrt(n)),
                    "ols_S_mean_rel_err": float(np.mean(col["ols_S_rel_err"])),
                    "ols_k_f_mean_rel_err": float(np.mean(col["ols_k_f_rel_err"])),
                    "ols_k_f_rel_err_sd": float(np.std(col["ols_k_f_rel_err"]))},
                "start_up": {"median_rls_vs_ridge_max_rel": statistics.median(col["rls_vs_ridge_max_rel"])},
                "discretisation": {"abs_H2_over_H9_minus_1_at_4Hz": col["H2_over_H9_minus_1"][0]},
                "covariance_forms": {k: _spread(col[f"z_{k}"]) for k in
                                     ("white_sigma2_P", "sandwich_lags_0", "sandwich_lags_2", "sandwich_lags_5")},
            })
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
