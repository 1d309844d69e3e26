"""Benchmark of the identification package; prints JSON (medians of repeated runs).

1. PSO+ at the paper's settings, Case I (150 particles, 1000 iterations, 100 points) and Case III
   (Section 5.1: 200 particles, 1000 iterations, Eq. 11, 200 points), four ways side by side in one
   process, same seed, the repeats interleaved: the compiled swarm (``swarm_kernel``), the same swarm
   in numpy (``run_pso(..., compiled=False)``: the whole swarm evaluated at once,
   ``batchfilter``), the numpy swarm with a per-particle ``scipy.signal.lfilter`` fitness, and the
   compiled reference: ``bench/swarm_reference.c`` (the plain per-particle difference equation and
   squared error) built now with the machine's C compiler (``cc -O3 -march=native``) and run through
   ctypes on the same swarm size for as many evaluations (iterations + 1).
   ``pso_ns_per_particle_sample``: the whole swarm run (updates, bookkeeping, random numbers,
   fitness) per particle, evaluation and sample; ``ratio`` = that over the reference's.
2. The expert estimator (sine fits + weighted LM, ``identify_fd``) against PSO+ on the same data:
   a simulated 5 kN stepped-sine run (config/sim-5kN.yaml).  ``expert_s`` with the sine fits computed
   each time; ``expert_same_data_again_s`` with them kept (``station/kept``: the same
   recording identified again in a process).  PSO+ gets every step (resampled to
   2 kHz, 200 points per step, Eq. 15 summed over steps, Eq. 11 mapped to k_f, b_f with the masses).

Usage: python bench/identify.py [--repeat N] [--swarm-only]
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import shutil
import subprocess
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from fractions import Fraction
from pathlib import Path

import numpy as np
from scipy.signal import resample_poly

from station.config import load_config
from station.ident.fd.identify import identify_fd
from station.ident.identify import identify_recording
from station.ident.inputs import model_for
from station.ident.models import DigitalTF
from station.ident.paper.batchfilter import batch_mse
from station.ident.paper.protocol import paper_data
from station.ident.paper.pso import (
    CASE_I,
    SECTION5_H2,
    output_error_objective,
    output_error_objective_loop,
    run_pso,
    split_h2,
)
from station.ident.response.frf import step_cache_clear
from station.paper import case_data
from station.recording import read_recording
from station.simulate import simulate_run

ROOT = Path(__file__).resolve().parents[1]


def timed(fn: Callable[[], object], repeat: int) -> tuple[float, object]:
    """Median wall time in s over ``repeat`` runs and the last result."""
    ts, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts)), out


def compiled_reference(tmp: str) -> tuple[Callable[..., object] | None, str]:
    """bench/swarm_reference.c built with the machine's C compiler; (function, how) or (None, why not)."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        return None, "no C compiler"
    lib_path = Path(tmp) / "swarm_reference.so"
    flags = ["-O3", "-march=native"]
    r = subprocess.run([cc, *flags, "-shared", "-fPIC", "-o", str(lib_path), str(ROOT / "bench" / "swarm_reference.c")],
                       capture_output=True, text=True)
    if r.returncode:
        return None, f"cc failed: {r.stderr.strip()[:200]}"
    lib = ctypes.CDLL(str(lib_path))
    dp = np.ctypeslib.ndpointer(np.float64, flags="C_CONTIGUOUS")
    lib.swarm_mse.argtypes = [dp, dp, dp, dp, ctypes.c_ssize_t, ctypes.c_ssize_t, dp]
    return lib.swarm_mse, " ".join([Path(cc).name, *flags])


def swarm_speed(name: str, form: str, x: np.ndarray, y: np.ndarray, settings, repeat: int,
                reference: Callable[..., object] | None) -> dict:
    n_dim = 4 if form == "h2" else 10
    s = replace(settings, variant="pso+")
    P, M, evals = s.n_particles, int(x.size), s.n_iterations + 1
    work = P * M * evals  # particle-samples of the whole run
    obj = output_error_objective(form, x, y)
    run_pso(obj, n_dim, replace(s, n_iterations=2), 0)  # compiled (or read from numba's cache) before timing
    X0 = np.random.default_rng(0).uniform(-s.x_max, s.x_max, (P, n_dim))  # the swarm's own first positions
    B, A = split_h2(X0)
    B, A, out = np.ascontiguousarray(B), np.ascontiguousarray(A), np.empty(P)
    xc, yc = np.ascontiguousarray(x, float), np.ascontiguousarray(y, float)

    def ref_run() -> None:
        assert reference is not None
        for _ in range(evals):
            reference(B, A, xc, yc, P, M, out)

    tc, tn, tr = [], [], []
    rc = rn = None
    for _ in range(repeat):  # interleaved: the compiled run, the numpy run and the reference see the same load
        t, rc = timed(lambda: run_pso(obj, n_dim, s, 0), 1)
        tc.append(t)
        t, rn = timed(lambda: run_pso(obj, n_dim, s, 0, compiled=False), 1)
        tn.append(t)
        if reference is not None:
            tr.append(timed(ref_run, 1)[0])
    assert rc is not None and rn is not None
    tl, rl = timed(lambda: run_pso(output_error_objective_loop(form, x, y), n_dim, s, 0), 1)
    pso_ns = float(np.median(tc)) / work * 1e9
    ref_ns = float(np.median(tr)) / work * 1e9 if tr else None
    return {"case": name, "particles": P, "iterations": s.n_iterations, "points": M,
            "pso_ns_per_particle_sample": pso_ns, "reference_ns_per_particle_sample": ref_ns,
            "ratio": pso_ns / ref_ns if ref_ns else None,
            "compiled_s": float(np.median(tc)), "numpy_s": float(np.median(tn)), "lfilter_loop_s": tl,
            "compiled_speedup_over_numpy": float(np.median(tn) / np.median(tc)),
            "same_result_to_the_bit": bool(np.array_equal(rc.mse_history, rn.mse_history)
                                            and np.array_equal(rc.position, rn.position)),
            "final_mse": rc.mse, "final_mse_lfilter_loop": rl.mse}


def stepped_objective(rec, fs_new: float, n_pts: int) -> tuple[Callable[[np.ndarray], np.ndarray], float]:
    """Eq. 15 summed over all steps for Eq. 11 particles; input a = -w^2 s (Eq. 2)."""
    parts = []
    ratio = Fraction(fs_new / rec.sample_rate_hz).limit_denominator(1000)
    for st in rec.steps:
        x, u = rec.step_signals(st)
        xs = resample_poly(x - x.mean(), ratio.numerator, ratio.denominator)
        us = resample_poly(u - u.mean(), ratio.numerator, ratio.denominator)
        e = int(0.05 * fs_new)
        w = 2 * np.pi * st.crank_frequency_hz
        parts.append((-(w**2) * xs[e:e + n_pts], us[e:e + n_pts]))

    def f(X: np.ndarray) -> np.ndarray:
        B, A = split_h2(X)
        return sum(batch_mse(B, A, xa, ya) for xa, ya in parts)

    return f, 1.0 / fs_new


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--swarm-only", action="store_true", help="part 1 only")
    args = ap.parse_args()
    out: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_config(ROOT / "config" / "sim-5kN.yaml")
        rec = read_recording(simulate_run(cfg, tmp, seed=1))
    truth = cfg.simulation.truth
    # 1. the swarm: compiled, numpy, lfilter loop and the compiled reference
    out["load_average_before"] = os.getloadavg()
    xi, yi = case_data("I")
    d5 = paper_data(rec)
    with tempfile.TemporaryDirectory() as tmp:
        reference, how = compiled_reference(tmp)
        rows = [swarm_speed("Case I (Sec. 4.1)", "h2", xi, yi, CASE_I, args.repeat, reference),
                swarm_speed("Case III (Sec. 5.1)", "h2", d5.x_id, d5.y_id, SECTION5_H2, args.repeat, reference)]
    out["reference"] = how
    out["pso_speed"] = rows
    out["pso_ns_per_particle_sample"] = {r["case"]: r["pso_ns_per_particle_sample"] for r in rows}
    out["reference_ns_per_particle_sample"] = {r["case"]: r["reference_ns_per_particle_sample"] for r in rows}
    out["ratio"] = {r["case"]: r["ratio"] for r in rows}
    if args.swarm_only:
        out["load_average_after"] = os.getloadavg()
        print(json.dumps(out, indent=2))
        return
    # 2. expert vs PSO+ on the same stepped-sine data
    def expert() -> object:
        step_cache_clear()  # the sine fits computed, not the ones kept from the repeat before
        return identify_fd(rec)

    te, fd = timed(expert, max(5, args.repeat))
    te_kept, _ = timed(lambda: identify_fd(rec), max(5, args.repeat))  # the same data again: steps kept
    k_fd, b_fd = fd.parameter("k_f"), fd.parameter("b_f")
    obj, T = stepped_objective(rec, 2000.0, 200)
    s5 = replace(SECTION5_H2, variant="pso+")
    tp, res = timed(lambda: run_pso(obj, 4, s5, 0), args.repeat)
    B, A = split_h2(res.position[None, :])
    theta = model_for(rec, "sdof").from_digital(DigitalTF(B[0], A[0], T))
    tp1, single = timed(lambda: identify_recording(rec, "pso+", "h2", seed=0), 1)
    th1 = single.extra["theta_from_coefficients"]
    out.update({
        "expert_s": te, "expert_same_data_again_s": te_kept, "pso_plus_stepped_s": tp, "expert_vs_pso_speedup": tp / te,
        "expert_k_f_rel_err": k_fd.value / truth.k_f - 1, "expert_b_f_rel_err": b_fd.value / truth.b_f - 1,
        "expert_k_f_rel_std": k_fd.std / k_fd.value, "expert_b_f_rel_std": b_fd.std / b_fd.value,
        "pso_k_f_rel_err": float(theta[1] / truth.k_f - 1), "pso_b_f_rel_err": float(theta[2] / truth.b_f - 1),
        "pso_stepped_final_mse_V2": res.mse,
        "paper_protocol_single_4Hz": {
            "pso_plus_s": tp1, "k_f_from_coefficients_rel_err": th1[1] / truth.k_f - 1,
            "b_f_from_coefficients_rel_err": th1[2] / truth.b_f - 1,
            "k_f_identifiable": single.parameter("k_f").identifiable,
            "b_f_identifiable": single.parameter("b_f").identifiable},
    })
    out["load_average_after"] = os.getloadavg()
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
