"""PNG of the gap shrinking: per-step gap (V) of the base model and after each added effect, with the
noise floor; the overall gap per stage; k_f and b_f before and after."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from station.discrepancy.result import DiscrepancyResult


def plot_report(rep: DiscrepancyResult, path: str | Path) -> Path:
    """Write the figure to ``path`` (PNG); returns the path."""
    p = Path(path)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2), gridspec_kw={"width_ratios": [2, 1]})
    f = list(rep.f_hz)
    stages = [("base model", rep.base_gap_steps)] + [(f"+ {e.name}", e.gap_steps_after) for e in rep.effects]
    for label, g in stages:
        ax1.semilogy(f, g, "o-", label=label)
    ax1.axhline(rep.noise_floor_V, color="k", ls="--", lw=1, label="noise floor")
    ax1.set_xscale("log")
    ax1.set_xlabel("crank frequency (Hz)")
    ax1.set_ylabel("RMS force residual per step (V)")
    ax1.legend(fontsize=8)
    ax1.grid(True, which="both", alpha=0.3)
    names = ["base"] + [e.name.replace("_", "\n") for e in rep.effects]
    gaps = [rep.base_gap] + [e.gap_after for e in rep.effects]
    ax2.bar(range(len(gaps)), gaps, color="tab:blue")
    ax2.axhline(rep.noise_floor_V, color="k", ls="--", lw=1)
    ax2.set_yscale("log")
    ax2.set_xticks(range(len(gaps)), names, fontsize=7)
    ax2.set_ylabel("overall gap (V)")
    lines = []
    for name, unit in (("k_f", "N/m"), ("b_f", "N s/m")):
        b, a = rep.parameters_before.get(name), rep.parameters_after.get(name)
        if b is not None and a is not None and b.identifiable and a.identifiable:
            lines.append(f"{name}: {b.value:.6g} ± {b.std:.2g} -> {a.value:.6g} ± {a.std:.2g} {unit}")
    title = (f"model gap: {rep.base_gap:.3g} V -> {rep.final_gap:.3g} V "
             f"(noise floor {rep.noise_floor_V:.3g} V)")
    fig.suptitle("\n".join([title, "; ".join(lines)]) if lines else title, fontsize=9)
    fig.tight_layout()
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p
