"""PNG figures for ``station paper`` (matplotlib, Agg backend): convergence, noise study, Section 5
testing results and the expert frequency-response fit."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from scipy.signal import lfilter

from station.ident.models import SdofModel


def _save(fig: Any, path: Path) -> Path:
    """Lay the figure out, write it to ``path`` as a 100 dpi PNG, free it; returns ``path``."""
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _convergence(out: Path, t1: dict[str, Any]) -> list[Path]:
    paths = []
    for case, t in t1.items():
        runs = t["runs"][0]["_runs"]
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        for v, r in runs.items():
            ax[0].semilogy(np.maximum(r.mse_history, 1e-40), label=v)
        ax[0].set(xlabel="iteration", ylabel="Gbest MSE (Eq. 15)", title=f"Case {case}: MSE of Gbest")
        ax[0].legend()
        ax[1].plot(runs["pso+"].fitness_history, label="PSO+ exp(-MSE) (Eq. 16)")
        ax[1].set(xlabel="iteration", ylabel="fitness", title=f"Case {case}: PSO+ fitness as plotted")
        ax[1].legend()
        paths.append(_save(fig, out / f"case{case}_convergence.png"))
    return paths


def _noise(out: Path, noise: dict[str, Any]) -> Path:
    rows = noise["rows"]
    fig, ax = plt.subplots(figsize=(6, 4))
    snr = [r["snr_db"] for r in rows]
    ax.semilogy(snr, [r["mse"] for r in rows], "o-", label="ours: PSO+ MSE")
    ax.semilogy(snr, [r["noise_variance"] for r in rows], "k--", label="added noise variance")
    ax.semilogy(snr, [r["paper_mse"] for r in rows], "s:", label="paper Fig. 15")
    ax.set(xlabel="SNR (dB)", ylabel="MSE", title="Section 4.2 noise study")
    ax.legend()
    return _save(fig, out / "noise_study.png")


def _section5(out: Path, sec5: dict[str, Any]) -> list[Path]:
    paths = []
    for name, row in sec5.items():
        d = row["_data"]
        fig, ax = plt.subplots(1, 2, figsize=(11, 4))
        t = np.arange(d.x_test.size) * d.T
        ax[0].plot(t, d.y_test, "k", lw=2, label="measured (test window)")
        for key, lab in (("_pso_h2", "PSO+ Eq. 11"), ("_rls", "RLS Eq. 17")):
            res = row[key]
            ax[0].plot(t, lfilter(res.extra["b"], res.extra["a"], d.x_test), label=lab)
        ax[0].set(xlabel="t (s)", ylabel="force signal (V)", title=f"{name}: testing")
        ax[0].legend()
        fd = row["_fd"]
        f = np.array(fd.extra["f_hz"])
        ff = np.linspace(1, max(f) * 1.2, 300)
        th = [fd.parameter(n).value for n in ("S", "k_f", "b_f")]
        model = SdofModel(fd.extra["m_e_kg"], fd.extra["m_l_kg"])
        static = abs(model.response(th, np.array([0.0]))[0])  # S M
        ax[1].plot(f, np.array(fd.extra["H_abs"]) / static, "o", label="measured |H| / (S M)")
        ax[1].plot(ff, np.abs(model.response(th, ff)) / static, label="FD fit (Eq. 9)")
        ax[1].set(xlabel="f (Hz)", ylabel="relative gain", title=f"{name}: expert FD fit")
        ax[1].legend()
        paths.append(_save(fig, out / f"section5_{name}.png"))
    return paths


def save_plots(out: Path, t1: dict[str, Any], noise: dict[str, Any], sec5: dict[str, Any]) -> list[Path]:
    """All figures; returns their paths."""
    return [*_convergence(out, t1), _noise(out, noise), *_section5(out, sec5)]
