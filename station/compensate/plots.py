"""Plots of compensation: the Bode plot of transducer, filter and compensated system with their
uncertainty bands (k = 2), and the measured and compensated signal with the estimate's band."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from station.compensate.design import CompensationFilter, bode


def bode_plot(filt: CompensationFilter, path: str | Path) -> Path:
    """PNG: magnitude (normalised to the static value, dB) and phase (deg) of the transducer G, the
    filter F and the compensated system F G (delay removed), bands k = 2; band and cut-off marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    b = bode(filt, 200)
    f = b.f
    g0 = abs(filt.sensor.response([0.0])[0])
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
    for H, u, label, norm in ((b.G, b.u_G_rel, "transducer G / G(0)", g0), (b.F, b.u_F_rel, "filter F G(0)", 1 / g0),
                              (b.Hc, b.u_Hc_rel, "compensated F G", 1.0)):
        m = np.abs(H) / norm
        line, = a1.semilogx(f, 20 * np.log10(m), label=label)
        a1.fill_between(f, 20 * np.log10(np.clip(m * (1 - 2 * u), 1e-12, None)), 20 * np.log10(m * (1 + 2 * u)),
                        color=line.get_color(), alpha=0.25)
    ph = np.degrees(np.unwrap(np.angle(b.Hc)))
    a2.semilogx(f, np.degrees(np.unwrap(np.angle(b.G))), label="transducer")
    a2.semilogx(f, ph, label="compensated (delay removed)")
    a2.fill_between(f, ph - 2 * np.degrees(b.u_Hc_phase), ph + 2 * np.degrees(b.u_Hc_phase), alpha=0.25)
    for ax in (a1, a2):
        ax.axvspan(max(filt.spec.band_hz[0], f[0]), filt.spec.band_hz[1], color="0.9", zorder=0)
        ax.axvline(filt.spec.cutoff_hz, color="0.5", ls="--", lw=0.8)
        ax.grid(True, which="both", alpha=0.3)
    a1.set_ylabel("magnitude / dB")
    a1.set_ylim(-40, 40)
    a2.set_ylabel("phase / deg")
    a2.set_xlabel("frequency / Hz")
    a1.legend(loc="lower left", fontsize=8)
    a1.set_title(f"compensation filter: {len(filt.b)} taps at {filt.sample_rate_hz:g} Hz, "
                 f"delay {filt.delay_s * 1e3:.4g} ms, cut-off {filt.spec.cutoff_hz:g} Hz (bands k = 2)", fontsize=9)
    fig.subplots_adjust(left=0.1, right=0.97, top=0.94, bottom=0.08, hspace=0.08)
    p = Path(path)
    fig.savefig(p, dpi=90)
    plt.close(fig)
    return p


def signal_plot(time_s: NDArray[np.float64], measured: NDArray[np.float64], est_time_s: NDArray[np.float64],
                estimate: NDArray[np.float64], u: NDArray[np.float64], static_gain: float, unit: str,
                path: str | Path) -> Path:
    """PNG: the measured signal divided by the static gain (what an uncompensated reading gives) and
    the compensated estimate with its band (k = 2) on its own time axis (the delay removed), in ``unit``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.5))
    ax.plot(time_s, measured / static_gain, lw=0.8, label="measured / static sensitivity")
    ax.plot(est_time_s, estimate, lw=0.9, label="compensated")
    ax.fill_between(est_time_s, estimate - 2 * u, estimate + 2 * u, alpha=0.3, label="compensated +- 2u")
    ax.set_xlabel("time / s")
    ax.set_ylabel(f"{unit}")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    p = Path(path)
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p
