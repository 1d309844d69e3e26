"""Result plots of a run as PNG bytes (matplotlib's Agg canvas, no pyplot state: safe in threads).

``render_plot(path, name)`` with ``name`` in ``PLOT_NAMES``:

* ``bode``: dynamic sensitivity S_dyn = -H/M (magnitude, V/N, and phase, degrees) of the measured
  steps with expanded (k = 2) error bars, and the identified model with its k = 2 band;
* ``timefit``: force signal and the model's prediction over three periods of (up to) four steps;
* ``residuals``: residual RMS of every step (whole record window) against frequency, and the
  residual over ten periods around the centre of (up to) four steps;
* ``convergence``: Gbest MSE per iteration of the stored PSO/PSO+ identifications (paper Eq. 15),
  else the stored fit's χ² per Levenberg–Marquardt iteration (``extra.cost_history``: fd stores
  it, from the linear start to the final χ²); else a figure saying that no iterative method was run.

Every figure is FIG_SIZE_PX pixels, rendered deterministically (no timestamps in the PNG).  The PNGs
of the last 16 recordings are kept (keyed like ``data.load_run``: path, modification time, size, the
versions of the stored results a plot reads), so the report page, its PDF and the page's plot requests draw each once.
"""

from __future__ import annotations

import io
import logging
import threading
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg, RendererAgg
from matplotlib.figure import Figure
from PIL import Image

from station.ident.names import SWARM_METHODS
from station.report.data import RunData, RunKey, StepTrace, load_run, run_key
from station.report.names import PLOT_NAMES, plotted
from station.report.quantities import COVERAGE_K, measured_sensitivity, model_sensitivity

log = logging.getLogger(__name__)
FIG_SIZE_PX = (900, 600)
DPI = 100
MAX_TRACES = 4


_renderers = threading.local()


class _Canvas(FigureCanvasAgg):
    """An Agg canvas that draws with its thread's one renderer of the figure's size instead of a new one
    per figure: matplotlib keeps text extents and parsed mathtext (the log axes' tick labels) per
    renderer, so the plots after the first reuse them rather than measuring and parsing the same
    labels again.  The renderer is cleared before each draw (``FigureCanvasAgg.draw``): the same
    pixels as a renderer of its own.  The picture is read (``png``) before the thread draws another."""

    def get_renderer(self) -> RendererAgg:
        w, h = self.get_width_height(physical=True)
        key = (w, h, self.figure.dpi)
        kept: dict[tuple[int, int, float], RendererAgg] = _renderers.__dict__.setdefault("by_size", {})
        if key not in kept:
            kept[key] = RendererAgg(w, h, self.figure.dpi)
        self.renderer = kept[key]
        self._lastKey = key  # type: ignore[assignment]  # matplotlib types it as None only
        return self.renderer


def _figure() -> Figure:
    fig = Figure(figsize=(FIG_SIZE_PX[0] / DPI, FIG_SIZE_PX[1] / DPI), dpi=DPI)
    _Canvas(fig)
    return fig


def png(fig: Figure) -> bytes:
    """The figure drawn on its Agg canvas as an RGB PNG (DPI stated, no text chunks).  The figure is
    opaque (white face), so the canvas' alpha is 255 everywhere and is left out: the same picture as
    ``savefig``'s RGBA PNG, a quarter fewer bytes to compress, and a PDF engine need not split off an
    alpha mask (WeasyPrint re-encodes an RGBA image as two).  zlib's fastest level: a quarter of the
    encoding time of its default for about a tenth more bytes (the pixels are the same)."""
    canvas = fig.canvas
    assert isinstance(canvas, FigureCanvasAgg)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    opaque = bool(np.all(rgba[..., 3] == 255))
    buf = io.BytesIO()
    Image.fromarray(rgba[..., :3] if opaque else rgba).save(
        buf, format="png", dpi=(DPI, DPI), compress_level=1)
    return buf.getvalue()


def _title(fig: Figure, d: RunData, what: str) -> None:
    fig.suptitle(f"{what}: {d.rec.transducer_id}, run {d.rec.run_id}", fontsize=10)


def _note(ax: Axes, text: str) -> None:
    if text:
        ax.text(0.01, 0.02, text, transform=ax.transAxes, fontsize=7, color="0.3", va="bottom", wrap=True)


def _bode(d: RunData, fig: Figure) -> None:
    ax_m, ax_p = fig.subplots(2, 1, sharex=True)
    fig.subplots_adjust(left=0.09, right=0.98, top=0.92, bottom=0.09, hspace=0.08)
    r, M = d.response, d.mass_kg
    mag, u_mag, ph, u_ph = measured_sensitivity(r.H, r.cov, M)
    f_lo, f_hi = float(np.min(r.f_hz)), float(np.max(r.f_hz))
    if d.curve is not None:
        ff = np.geomspace(0.5 * f_lo, 1.5 * f_hi, 400)
        m_mag, m_umag, m_ph, m_uph = model_sensitivity(d.curve, ff)
        ph_at = np.interp(r.f_hz, ff, m_ph)
        ph = ph_at + np.angle(np.exp(1j * (ph - ph_at)))  # measured phase on the model's branch
        label = f"model {d.ident.model} ({d.ident.method})"
        inside = (ff >= f_lo) & (ff <= f_hi)  # the plan's range; outside it the model is extrapolated
        outside = np.where(inside, np.nan, 1.0)
        ax_m.plot(ff, 1e3 * m_mag * np.where(inside, 1.0, np.nan), "C1", label=label)
        ax_p.plot(ff, np.degrees(m_ph) * np.where(inside, 1.0, np.nan), "C1", label=label)
        ax_m.plot(ff, 1e3 * m_mag * outside, "C1", ls=":", lw=1, label="model extrapolated beyond the plan")
        ax_p.plot(ff, np.degrees(m_ph) * outside, "C1", ls=":", lw=1)
        for ax in (ax_m, ax_p):
            ax.axvspan(ff[0], f_lo, color="0.9", lw=0)
            ax.axvspan(f_hi, ff[-1], color="0.9", lw=0)
        if m_umag is not None and m_uph is not None:
            m_umag, m_uph = np.where(inside, m_umag, np.nan), np.where(inside, m_uph, np.nan)
            ax_m.fill_between(ff, 1e3 * (m_mag - COVERAGE_K * m_umag), 1e3 * (m_mag + COVERAGE_K * m_umag),
                              color="C1", alpha=0.25, lw=0, label="model, k = 2")
            ax_p.fill_between(ff, np.degrees(m_ph - COVERAGE_K * m_uph), np.degrees(m_ph + COVERAGE_K * m_uph),
                              color="C1", alpha=0.25, lw=0)
    ax_m.errorbar(r.f_hz, 1e3 * mag, yerr=1e3 * COVERAGE_K * u_mag, fmt="o", color="C0", capsize=3,
                  label=f"measured, U (k = 2) ≤ {100 * COVERAGE_K * np.max(u_mag / mag):.2g} % of |S_dyn|")
    ax_p.errorbar(r.f_hz, np.degrees(ph), yerr=np.degrees(COVERAGE_K * u_ph), fmt="o", color="C0", capsize=3)
    ax_m.set(ylabel="|S_dyn| (mV/N)", xscale="log")
    ax_p.set(ylabel="phase of S_dyn (°)", xlabel="crank frequency f (Hz)", xscale="log")
    ax_m.legend(fontsize=8, loc="upper left")
    for ax in (ax_m, ax_p):
        ax.grid(True, which="both", alpha=0.3)
    _note(ax_p, d.curve_note or (d.curve.note if d.curve else ""))
    _title(fig, d, f"Dynamic sensitivity S_dyn = -H/M (M = {M:.4g} kg)")


def _pick(traces: tuple[StepTrace, ...]) -> list[StepTrace]:
    if len(traces) <= MAX_TRACES:
        return list(traces)
    idx = np.unique(np.round(np.linspace(0, len(traces) - 1, MAX_TRACES)).astype(int))
    return [traces[i] for i in idx]


def _grid(fig: Figure, n: int) -> list[Axes]:
    rows, cols = (n, 1) if n <= 2 else ((n + 1) // 2, 2)
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    fig.subplots_adjust(left=0.08, right=0.98, top=0.89, bottom=0.09, hspace=0.45, wspace=0.25)
    for ax in axes[n:]:
        ax.set_visible(False)
    return list(axes[:n])


def _timefit(d: RunData, fig: Figure) -> None:
    shown = _pick(d.traces)
    for ax, tr in zip(_grid(fig, len(shown)), shown, strict=True):
        keep = np.flatnonzero(np.abs(tr.t_s) <= 1.5 / tr.f_hz)  # three periods around the window's centre
        keep = keep[:: max(1, keep.size // 900)]  # at most ~900 points per panel (render time)
        t_ms = 1e3 * tr.t_s[keep]
        ax.plot(t_ms, tr.u_V[keep], ".", ms=2, color="C0", label="measured")
        if tr.model_V is not None:
            ax.plot(t_ms, tr.model_V[keep], "C1", lw=1.2, label="model")
        ax.set(title=f"step {tr.index}: {tr.f_hz:.4g} Hz", xlabel="t - t_centre (ms)", ylabel="force signal (V)")
        ax.title.set_fontsize(9)
        ax.grid(True, alpha=0.3)
    fig.axes[0].legend(fontsize=8, loc="upper right")
    if d.curve is None:
        _note(fig.axes[0], d.curve_note)
    _title(fig, d, f"Time-domain fit ({len(shown)} of {len(d.traces)} steps)")


def _residuals(d: RunData, fig: Figure) -> None:
    if d.curve is None:
        ax = fig.subplots()
        ax.axis("off")
        ax.text(0.5, 0.5, f"No residuals: {d.curve_note}", ha="center", va="center", wrap=True)
        _title(fig, d, "Residuals")
        return
    shown = _pick(d.traces)
    gs = fig.add_gridspec(2, len(shown), height_ratios=(1, 1.3), left=0.08, right=0.98, top=0.91, bottom=0.09,
                          hspace=0.45, wspace=0.3)
    ax0 = fig.add_subplot(gs[0, :])
    f = np.array([tr.f_hz for tr in d.traces])
    rms = np.array([np.sqrt(np.mean((tr.u_V - tr.model_V) ** 2)) for tr in d.traces if tr.model_V is not None])
    ax0.plot(f, 1e3 * rms, "o-", color="C3")
    ax0.set(xscale="log", xlabel="crank frequency f (Hz)", ylabel="residual RMS (mV)", ylim=(0, None))
    ax0.grid(True, which="both", alpha=0.3)
    for j, tr in enumerate(shown):
        ax = fig.add_subplot(gs[1, j])
        assert tr.model_V is not None
        keep = np.flatnonzero(np.abs(tr.t_s) <= 5.0 / tr.f_hz)  # ten periods: a misfit shows as a wave
        keep = keep[:: max(1, keep.size // 2000)]
        ax.plot(1e3 * tr.t_s[keep], 1e3 * (tr.u_V - tr.model_V)[keep], lw=0.6, color="C3")
        ax.set_title(f"step {tr.index}: {tr.f_hz:.4g} Hz", fontsize=9)
        ax.set(xlabel="t - t_centre (ms)")
        if j == 0:
            ax.set_ylabel("force residual (mV)")
        ax.grid(True, alpha=0.3)
    _title(fig, d, "Residuals: measured force signal - model")


def _placeholder(fig: Figure, d: RunData, text: str) -> None:
    ax = fig.subplots()
    ax.axis("off")
    ax.text(0.5, 0.5, text, ha="center", va="center", fontsize=11, wrap=True)
    _title(fig, d, "Convergence")


def _convergence(d: RunData, fig: Figure) -> None:
    runs = sorted((r for r in d.results.values() if r.name.startswith("identify_")
                   and r.payload.get("method") in SWARM_METHODS
                   and (r.payload.get("extra") or {}).get("mse_history")), key=lambda r: r.name)
    if runs:
        ax = fig.subplots()
        for r in runs:
            ex = r.payload["extra"]
            hist = np.maximum(np.asarray(ex["mse_history"], float), 1e-300)
            stride = max(1, int(ex.get("n_iterations", len(hist) - 1)) // 200)
            ax.semilogy(np.arange(hist.size) * stride, hist,
                        label=f"{r.payload['method'].upper()} on {r.payload.get('model')} (seed {ex.get('seed')}), "
                              f"converged at iteration {ex.get('iterations_to_converge')}")
        ax.set(xlabel="iteration", ylabel="Gbest MSE (V², paper Eq. 15)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        _title(fig, d, "Convergence of the particle swarm")
        return
    hist_runs = [r for r in d.results.values() if (r.payload.get("extra") or {}).get("cost_history")]
    if hist_runs:
        ax = fig.subplots()
        for r in hist_runs:
            ex = r.payload["extra"]
            hist = np.asarray(ex["cost_history"], float)
            dof = ex.get("dof")
            final = hist[-1]
            gap = np.maximum(hist - final, 1e-16 * max(final, 1e-300))  # what each iteration had left to gain
            per = f", final χ²/dof {final / dof:.3g}" if isinstance(dof, int) and dof > 0 else ""
            ax.semilogy(np.arange(hist.size), gap, "o-",
                        label=f"{r.name}: χ² {hist[0]:.6g} at the start → {final:.6g} after {hist.size - 1} "
                              f"iteration(s){per}")
        ax.set(xlabel="Levenberg–Marquardt iteration (0: the linear start on 1/H)",
               ylabel="χ² − final χ² (weighted H(f) residual)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        _title(fig, d, "Convergence of the frequency-domain fit")
        return
    _placeholder(fig, d, "No iterative method was run on this recording.\n\n"
                 f"The identification shown ({d.ident.method}, {d.ident.model}) stores no "
                 "iteration history.\nRun `station identify --method pso+ RECORDING` to see the "
                 "paper's PSO+ convergence here.")


_RENDERERS: dict[str, Callable[[RunData, Figure], None]] = {
    "bode": _bode, "timefit": _timefit, "residuals": _residuals, "convergence": _convergence}


def make_figure(data: RunData, name: str) -> Figure:
    """The figure ``name`` of loaded run data (used by render_plot and the PDF report)."""
    if name not in _RENDERERS:
        raise KeyError(f"unknown plot {name!r}; expected one of {', '.join(PLOT_NAMES)}")
    fig = _figure()
    _RENDERERS[name](data, fig)  # fixed margins: a layout engine would draw every figure twice
    return fig


def render_plot(recording_path: Path, name: str) -> bytes:
    """PNG of the plot ``name`` (one of PLOT_NAMES) for a recording.  KeyError for an unknown name;
    RecordingFormatError when the recording is unreadable or has no results and none can be computed."""
    if name not in _RENDERERS:
        raise KeyError(f"unknown plot {name!r}; expected one of {', '.join(PLOT_NAMES)}")
    path, mtime_ns, size, version = run_key(recording_path)
    return cached_png((path, mtime_ns, size, plotted(version)), name)


@lru_cache(maxsize=16 * len(PLOT_NAMES))  # PNGs of 60-90 kB: at most about 6 MB
def cached_png(key: RunKey, name: str) -> bytes:
    """The cache behind :func:`render_plot`: PNG of plot ``name`` of the recording ``key``
    (``data.run_key`` without the results no plot reads, ``names.plotted``; the data from
    ``data.load_run``).  ``cached_png.cache_clear()`` drops the (up to 64) kept PNGs."""
    return png(make_figure(load_run(key[0]), name))
